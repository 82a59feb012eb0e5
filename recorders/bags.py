"""Foreign logs through the ``rosbags`` library: which files form a bag, opening it, its topics.

lcv-replay writes no bag reader: ROS 1 bags, ROS 2 bag folders (``metadata.yaml`` with ``.db3`` or
``.mcap`` files) and bare ROS 2 ``.db3``/``.mcap`` files are read with ``rosbags``'
:class:`~rosbags.highlevel.AnyReader`, which deserialises with the message definitions stored in the
bag (a bag without them falls back to the ROS 2 Humble typestore).

This module owns:

* :func:`resolve_source`: the paths a user names -> a :class:`BagSource` (split ROS 1 bags in part
  order, a ROS 2 folder for its ``metadata.yaml`` or data file), refusing a missing split part or a
  ``metadata.yaml`` without its data files by name;
* :func:`open_bag`: an opened ``AnyReader`` whose errors become :class:`RecorderError`;
* the topic kinds lcv-replay can use (:data:`IMAGE_TYPES`, :data:`POSE_TYPES`, ...) and
  :func:`pick_topics`, which chooses the topics a user did not name (one candidate: taken, with a
  note; several: an error listing them with the flag to choose);
* :func:`inspect_bag` / :func:`format_bag_info`: ``lcv-replay info`` on a foreign log.
"""

from __future__ import annotations

import contextlib
import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Literal, Mapping, Sequence

import numpy as np

from lcv_replay.errors import RecorderError

log = logging.getLogger(__name__)

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
CAMERA_INFO_TYPES = ("sensor_msgs/msg/CameraInfo",)
ODOMETRY_TYPES = ("nav_msgs/msg/Odometry",)
POSE_TYPES = ("nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseWithCovarianceStamped")
TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")
TF_TOPICS = ("/tf", "/tf_static", "tf", "tf_static")
#: Topic names that mean ground truth (motion capture, RTK, a simulator's truth).
GROUND_TRUTH_NAME = re.compile(r"ground[_-]?truth|(^|[/_])gt($|[/_])|vicon|mocap|optitrack|qualisys", re.IGNORECASE)
#: Pairs of name parts that mark the two cameras of a stereo rig.
STEREO_NAME_PAIRS = (("left", "right"), ("cam0", "cam1"), ("infra1", "infra2"), ("camera_l", "camera_r"))

Storage = Literal["rosbag1", "sqlite3", "mcap"]
_SPLIT_PART = re.compile(r"^(?P<stem>.+)_(?P<index>\d+)\.bag$")
_MCAP_MAGIC = b"\x89MCAP0\r\n"


def is_static_tf_topic(topic: str) -> bool:
    return topic.lstrip("/") == "tf_static"


# ---------------------------------------------------------------------------------------------
# Which files form the bag
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BagSource:
    """A foreign log as ``rosbags`` opens it.

    Attributes:
        kind: ``"ros1"``, ``"ros2"``, or ``"mcap"`` (any other MCAP, for ``info`` only).
        storage: ``"rosbag1"``, ``"sqlite3"`` or ``"mcap"``.
        paths: what ``AnyReader`` opens: the ``.bag`` files in split-part order, or one ROS 2 bag
            folder, ``.db3`` or ``.mcap`` file.
        files: the data files (sizes, content hash), in order.
        name: a short name for messages and default outputs (the bag's stem).
    """

    kind: Literal["ros1", "ros2", "mcap"]
    storage: Storage
    paths: tuple[Path, ...]
    files: tuple[Path, ...]
    name: str

    @property
    def display(self) -> str:
        """The path (or first and last split part) as the user named it."""
        if len(self.paths) == 1:
            return str(self.paths[0])
        return f"{self.paths[0]} .. {self.paths[-1].name} ({len(self.paths)} parts)"

    @property
    def size_bytes(self) -> int:
        return sum(f.stat().st_size for f in self.files)

    @property
    def beside(self) -> Path:
        """The folder that holds the bag (where ``--keep-converted`` writes)."""
        first = self.paths[0]
        return first.parent if str(first.parent) else Path(".")


def mcap_profile(path: Path) -> str | None:
    """The ``profile`` of an MCAP file's header record (``"ros2"`` for ROS 2 bags), or ``None`` if not MCAP."""
    try:
        with open(path, "rb") as f:
            head = f.read(8 + 9 + 4 + 256)
    except OSError:
        return None
    if len(head) < 8 + 9 + 4 or head[:8] != _MCAP_MAGIC or head[8] != 0x01:
        return None
    length = int.from_bytes(head[17:21], "little")
    return head[21 : 21 + length].decode(errors="replace")


def is_foreign_log(path: str | Path) -> bool:
    """Whether ``path`` is a ROS bag (ROS 1 ``.bag``, a ROS 2 folder, ``.db3``, ``metadata.yaml``,
    or an MCAP with the ``ros2`` profile) rather than an lcv-replay log."""
    path = Path(path)
    if path.is_dir():
        return (path / "metadata.yaml").is_file() or any(path.glob("*.bag"))
    suffix = path.suffix.lower()
    if suffix in (".bag", ".db3") or path.name == "metadata.yaml":
        return True
    if suffix == ".mcap" or path.is_file():
        return mcap_profile(path) == "ros2"
    return False


def resolve_source(paths: Sequence[str | Path]) -> BagSource:
    """The bag the user named: one or several ROS 1 ``.bag`` files, or one ROS 2 bag.

    * ROS 1: the ``.bag`` files (or a folder of them) in split-part order (``NAME_0.bag``,
      ``NAME_1.bag``, ...); a gap in the part numbers is an error naming the missing part.
    * ROS 2: a bag folder, its ``metadata.yaml`` or one of its files (the folder is used), or a
      bare ``.db3``/``.mcap``; every data file that ``metadata.yaml`` lists must exist.

    Raises:
        RecorderError: a path is missing, the formats are mixed, a split part or data file is
            missing, or the path is no bag.
    """
    if not paths:
        raise RecorderError("no bag given", fix="pass a ROS 1 .bag, a ROS 2 bag folder, a .db3 or a ROS 2 .mcap")
    resolved: list[Path] = []
    for raw in paths:
        path = Path(raw)
        if not path.exists():
            raise RecorderError("file not found", path=path, fix="check the path")
        if path not in resolved:
            resolved.append(path)
    if len(resolved) == 1 and resolved[0].is_dir() and not (resolved[0] / "metadata.yaml").exists():
        parts = sorted(resolved[0].glob("*.bag"))
        if not parts:
            data = sorted(p.name for p in resolved[0].iterdir() if p.suffix in (".db3", ".mcap"))
            raise RecorderError(
                "folder has no metadata.yaml and no .bag files",
                path=resolved[0],
                fix=f"pass one of its data files ({', '.join(data)})" if data else "pass a ROS 1 .bag, a ROS 2 bag folder, a .db3 or a .mcap",
            )
        resolved = parts
    ros1 = [p for p in resolved if p.suffix.lower() == ".bag"]
    if ros1:
        if len(ros1) != len(resolved):
            other = next(p for p in resolved if p not in ros1)
            raise RecorderError("cannot mix ROS 1 .bag files with other inputs", path=other, fix="import one bag at a time")
        ordered = _split_order(ros1)
        return BagSource("ros1", "rosbag1", tuple(ordered), tuple(ordered), _split_stem(ordered[0]))
    if len(resolved) > 1:
        raise RecorderError(
            f"{len(resolved)} inputs given; a ROS 2 bag is one folder (or one .db3/.mcap)",
            path=resolved[1],
            fix="pass the bag folder that holds metadata.yaml",
        )
    return _ros2_source(resolved[0])


def _split_stem(path: Path) -> str:
    match = _SPLIT_PART.match(path.name)
    return match.group("stem") if match else path.stem


def _split_order(files: list[Path]) -> list[Path]:
    """ROS 1 split parts in part order; a gap in ``NAME_<k>.bag`` numbering is a missing part."""
    groups: dict[tuple[Path, str], list[tuple[int, Path]]] = {}
    plain: list[Path] = []
    for path in files:
        match = _SPLIT_PART.match(path.name)
        if match:
            groups.setdefault((path.parent, match.group("stem")), []).append((int(match.group("index")), path))
        else:
            plain.append(path)
    ordered: list[Path] = list(plain)
    for (folder, stem), parts in sorted(groups.items(), key=lambda kv: (str(kv[0][0]), kv[0][1])):
        parts.sort()
        indices = [k for k, _ in parts]
        expected = range(indices[0], indices[-1] + 1)
        missing = [k for k in expected if k not in indices]
        if missing:
            names = ", ".join(f"{stem}_{k}.bag" for k in missing)
            on_disk = all((folder / f"{stem}_{k}.bag").exists() for k in missing)
            raise RecorderError(
                f"split bag {stem}: part {names} is missing (given parts {', '.join(str(k) for k in indices)})",
                path=folder / f"{stem}_{missing[0]}.bag",
                fix=f"pass every part ({folder / stem}_*.bag)" if on_disk else "copy the missing part next to the others",
            )
        if indices[0] > 0:
            earlier = [folder / f"{stem}_{k}.bag" for k in range(indices[0])]
            present = [p.name for p in earlier if p.exists()]
            log.warning(
                "%s: the import starts at part %d of split bag %s%s",
                parts[0][1], indices[0], stem,
                f"; parts {', '.join(present)} beside it are not included" if present else "; the earlier parts are missing",
            )
        ordered.extend(p for _, p in parts)
    return ordered


def _ros2_source(path: Path) -> BagSource:
    if path.name == "metadata.yaml":
        path = path.parent
    elif path.is_file() and (path.parent / "metadata.yaml").is_file() and path.suffix in (".db3", ".mcap"):
        listed = _metadata_files(path.parent)
        if path.name in {p.name for p in listed}:
            path = path.parent  # a file of a bag folder: the folder knows every part and the topic types
    if path.is_dir():
        files = _metadata_files(path)
        missing = [f for f in files if not f.exists()]
        if missing:
            raise RecorderError(
                f"metadata.yaml lists {', '.join(f.name for f in missing)}, which "
                f"{'is' if len(missing) == 1 else 'are'} not in the bag folder",
                path=path / "metadata.yaml",
                fix="copy the whole bag folder (metadata.yaml and every data file it lists)",
            )
        storage = _metadata_storage(path)
        return BagSource("ros2", storage, (path,), tuple(files), path.name)
    suffix = path.suffix.lower()
    if suffix == ".db3":
        return BagSource("ros2", "sqlite3", (path,), (path,), path.stem)
    if suffix == ".mcap" or mcap_profile(path) is not None:
        profile = mcap_profile(path)
        if profile is None:
            raise RecorderError("not a readable MCAP file (no MCAP magic bytes at the start)", path=path, fix="pass a ROS 2 .mcap bag")
        if profile != "ros2":
            raise RecorderError(
                f"this MCAP has the {profile!r} profile, not a ROS 2 bag's 'ros2'",
                path=path,
                fix="pass a bag recorded by 'ros2 bag record -s mcap' (an lcv-replay log is replayed as it is)",
            )
        return BagSource("ros2", "mcap", (path,), (path,), path.stem)
    raise RecorderError(
        "not a bag: expected a ROS 1 .bag, a ROS 2 bag folder (metadata.yaml), a .db3 or a ROS 2 .mcap",
        path=path,
        fix="check the path",
    )


def _metadata(folder: Path) -> dict:
    """``rosbag2_bagfile_information`` of a bag folder (to name its data files before rosbags opens it)."""
    from ruamel.yaml import YAML  # rosbags' own YAML parser (a dependency of rosbags)
    from ruamel.yaml.error import YAMLError

    try:
        data = YAML(typ="safe").load((folder / "metadata.yaml").read_text())
        return dict(data["rosbag2_bagfile_information"])
    except (OSError, YAMLError, KeyError, TypeError, ValueError) as exc:
        raise RecorderError(f"metadata.yaml cannot be read ({exc})", path=folder / "metadata.yaml", fix="copy the bag folder again") from None


def _metadata_files(folder: Path) -> list[Path]:
    return [folder / Path(str(name)).name for name in _metadata(folder).get("relative_file_paths", [])]


def _metadata_storage(folder: Path) -> Storage:
    storage = str(_metadata(folder).get("storage_identifier", ""))
    if storage not in ("sqlite3", "mcap"):
        raise RecorderError(f"storage plugin {storage!r} is not supported", path=folder / "metadata.yaml", fix="record with -s sqlite3 or -s mcap")
    return storage  # type: ignore[return-value]


# ---------------------------------------------------------------------------------------------
# Opening
# ---------------------------------------------------------------------------------------------


@contextlib.contextmanager
def open_bag(source: BagSource) -> Iterator[Any]:
    """An opened ``rosbags.highlevel.AnyReader`` on ``source``; its errors become :class:`RecorderError`."""
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.rosbag1 import ReaderError as Ros1ReaderError
    from rosbags.rosbag2 import ReaderError as Ros2ReaderError
    from rosbags.typesys import Stores, get_typestore

    fallback = get_typestore(Stores.ROS1_NOETIC if source.kind == "ros1" else Stores.ROS2_HUMBLE)
    try:
        reader = AnyReader(list(source.paths), default_typestore=fallback)
        reader.open()
    except (AnyReaderError, Ros1ReaderError, Ros2ReaderError, FileNotFoundError, OSError) as exc:
        raise bag_error(source, exc) from None
    try:
        yield reader
    finally:
        with contextlib.suppress(Exception):
            reader.close()


def bag_error(source: BagSource, exc: BaseException, what: str = "cannot be read") -> RecorderError:
    """A ``rosbags`` exception as one :class:`RecorderError` line with a fix."""
    text = " ".join(str(a) for a in exc.args) or type(exc).__name__
    fix = "the bag is damaged or incomplete; re-copy it"
    if "not indexed" in text:
        fix = "the recording was cut off; run 'rosbag reindex' on it (ROS 1) and try again"
    elif "missing" in text and source.kind == "ros2":
        fix = "copy the whole bag folder (metadata.yaml and every data file it lists)"
    elif "no type definitions" in text.lower():
        fix = "pass the bag folder with its metadata.yaml, or record with a ROS 2 release that stores definitions"
    return RecorderError(f"the bag {what}: {text}", path=source.paths[0], fix=fix)


def deserialize(reader: Any, source: BagSource, connection: Any, log_time_ns: int, raw: bytes) -> Any:
    """One message through the reader's typestore; a bad message is a :class:`RecorderError` naming it."""
    from rosbags.highlevel import AnyReaderError

    try:
        return reader.deserialize(raw, connection.msgtype)
    except (AnyReaderError, ValueError, IndexError, KeyError, AssertionError) as exc:
        raise RecorderError(
            f"a {connection.msgtype} message on {connection.topic} at {log_time_ns} ns cannot be decoded ({exc})",
            path=source.paths[0],
            fix="the bag is damaged; re-copy it or choose another topic",
        ) from None


def bag_topics(reader: Any) -> dict[str, str]:
    """``{topic: message type}`` of an opened reader (``""`` for a topic with several types)."""
    return {name: info.msgtype or "" for name, info in reader.topics.items()}


# ---------------------------------------------------------------------------------------------
# Picking the topics the user did not name
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TopicRequest:
    """What the user named. ``None`` = choose for me; ``""`` = none.

    ``odom_from_tf``/``ground_truth_from_tf`` are ``(parent, child)`` frame pairs.
    """

    left: str | None = None
    right: str | None = None
    no_images: bool = False
    odom: str | None = None
    odom_from_tf: tuple[str, str] | None = None
    ground_truth: str | None = None
    ground_truth_from_tf: tuple[str, str] | None = None


@dataclass(frozen=True)
class TopicPlan:
    """The topics an import uses, and notes on what was chosen for the user.

    ``odom``/``ground_truth`` are topic names or ``None``; with ``*_from_tf`` set, they come from
    the TF chain instead. ``notes`` are lines for the user ("odometry: /odom, the only candidate").
    """

    left: str | None = None
    right: str | None = None
    odom: str | None = None
    odom_from_tf: tuple[str, str] | None = None
    ground_truth: str | None = None
    ground_truth_from_tf: tuple[str, str] | None = None
    notes: tuple[str, ...] = ()

    @property
    def needs_tf(self) -> bool:
        return self.odom_from_tf is not None or self.ground_truth_from_tf is not None


@dataclass(frozen=True)
class TopicCandidates:
    """The topics of each kind lcv-replay can use, from a ``{topic: type}`` listing."""

    stereo_pairs: tuple[tuple[str, str], ...]
    images: tuple[str, ...]
    odometry: tuple[str, ...]  # nav_msgs/Odometry topics
    poses: tuple[str, ...]  # every pose type (Odometry, PoseStamped, PoseWithCovarianceStamped)
    ground_truth: tuple[str, ...]  # pose topics whose name means ground truth
    tf: tuple[str, ...]

    @classmethod
    def of(cls, topics: Mapping[str, str]) -> "TopicCandidates":
        images = tuple(sorted(t for t, ty in topics.items() if ty in IMAGE_TYPES))
        poses = tuple(sorted(t for t, ty in topics.items() if ty in POSE_TYPES))
        return cls(
            stereo_pairs=stereo_pairs(images),
            images=images,
            odometry=tuple(t for t in poses if topics[t] in ODOMETRY_TYPES and not GROUND_TRUTH_NAME.search(t)),
            poses=poses,
            ground_truth=tuple(t for t in poses if GROUND_TRUTH_NAME.search(t)),
            tf=tuple(sorted(t for t, ty in topics.items() if ty in TF_TYPES)),
        )

    def odometry_choices(self, ground_truth: str | None) -> tuple[str, ...]:
        """Odometry candidates: the ``nav_msgs/Odometry`` topics, else the other pose topics."""
        if self.odometry:
            return self.odometry
        return tuple(t for t in self.poses if t != ground_truth and t not in self.ground_truth)


def stereo_pairs(images: Sequence[str]) -> tuple[tuple[str, str], ...]:
    """``(left, right)`` image topics whose names differ only by ``left``/``right`` (or cam0/cam1, ...)."""
    pairs = []
    names = set(images)
    for topic in images:
        for a, b in STEREO_NAME_PAIRS:
            if a in topic:
                other = topic.replace(a, b)
                if other in names and other != topic:
                    pairs.append((topic, other))
    return tuple(sorted(set(pairs)))


def _listing(topics: Mapping[str, str], names: Sequence[str], counts: Mapping[str, int] | None = None) -> str:
    def one(t: str) -> str:
        n = counts.get(t) if counts else None
        return f"{t} ({topics.get(t, '?')}{f', {n} messages' if n is not None else ''})"

    return ", ".join(one(t) for t in names)


def check_topic_type(topics: Mapping[str, str], topic: str, accepted: Sequence[str], flag: str, *, path: Path | None = None) -> None:
    """A named topic must exist and carry one of the ``accepted`` types; else one error line listing the topics."""
    listing = ", ".join(f"{t} ({ty or 'several types'})" for t, ty in sorted(topics.items())) or "none"
    if topic not in topics:
        raise RecorderError(f"topic {topic} ({flag}) is not in the bag", path=path, fix=f"topics here: {listing}")
    if topics[topic] not in accepted:
        raise RecorderError(
            f"topic {topic} ({flag}) has type {topics[topic] or 'several types'}, which lcv-replay cannot use there; "
            f"expected {' or '.join(accepted)}",
            path=path,
            fix=f"topics here: {listing}",
        )


def pick_topics(
    topics: Mapping[str, str], request: TopicRequest, *, counts: Mapping[str, int] | None = None,
    path: Path | None = None, tf_hint: tuple[str, str] | None = None,
) -> TopicPlan:
    """Choose the topics the user did not name (see the module docstring).

    Args:
        topics: ``{topic: message type}`` of the bag.
        request: what the user named.
        counts: message counts, for the notes and errors.
        path: the bag, for error messages.
        tf_hint: a likely ``--odom-from-tf`` pair, offered when no odometry topic exists.

    Raises:
        RecorderError: a named topic is missing or of a type lcv-replay cannot use there; several
            candidates of a kind exist and none is named (the message lists them and the flag); no
            odometry and no images at all.
    """
    notes: list[str] = []
    cands = TopicCandidates.of(topics)

    # -- images
    left, right = request.left or None, request.right or None
    if request.no_images:
        left = right = None
    elif left is not None:
        check_topic_type(topics, left, IMAGE_TYPES, "--left-topic", path=path)
        if request.right is None:
            sibling = next((r for l, r in cands.stereo_pairs if l == left), None)
            if sibling is not None:
                right = sibling
                notes.append(f"right camera: {sibling} (the left topic's sibling; --right-topic to choose another)")
    elif request.right:
        raise RecorderError("--right-topic needs --left-topic", path=path, fix="name the left image topic too")
    elif cands.images:
        if len(cands.stereo_pairs) == 1:
            left, right = cands.stereo_pairs[0]
            notes.append(f"stereo pair: {left} / {right} (the only pair; --left-topic/--right-topic to choose, --no-images for none)")
        elif len(cands.stereo_pairs) > 1:
            listing = "; ".join(f"{l} / {r}" for l, r in cands.stereo_pairs)
            raise RecorderError(
                f"several stereo pairs: {listing}",
                path=path,
                fix="choose one with --left-topic and --right-topic (or --no-images)",
            )
        elif len(cands.images) == 1:
            left = cands.images[0]
            notes.append(f"camera: {left} (the only image topic, mono; --left-topic to choose, --no-images for none)")
        else:
            raise RecorderError(
                f"several image topics and no left/right pair among them: {_listing(topics, cands.images, counts)}",
                path=path,
                fix="choose with --left-topic (and --right-topic), or pass --no-images",
            )
    if right is not None and request.right is not None:
        check_topic_type(topics, right, IMAGE_TYPES, "--right-topic", path=path)

    # -- ground truth
    ground_truth = request.ground_truth or None
    gt_tf = request.ground_truth_from_tf
    if gt_tf is not None:
        ground_truth = None
    elif ground_truth is not None:
        check_topic_type(topics, ground_truth, POSE_TYPES, "--ground-truth-topic", path=path)
    elif request.ground_truth is None and cands.ground_truth:
        if len(cands.ground_truth) > 1:
            raise RecorderError(
                f"several ground-truth topics: {_listing(topics, cands.ground_truth, counts)}",
                path=path,
                fix="choose one with --ground-truth-topic (or --ground-truth-topic '' for none)",
            )
        ground_truth = cands.ground_truth[0]
        notes.append(f"ground truth: {ground_truth} ({topics[ground_truth]}; by its name; --ground-truth-topic '' for none)")

    # -- odometry
    odom = request.odom or None
    odom_tf = request.odom_from_tf
    if odom_tf is not None:
        odom = None
        if not cands.tf:
            raise RecorderError(
                "--odom-from-tf needs /tf or /tf_static, and the bag has neither",
                path=path,
                fix=f"use a pose topic with --odom-topic ({_listing(topics, cands.poses, counts) or 'none in this bag'})",
            )
    elif odom is not None:
        check_topic_type(topics, odom, POSE_TYPES, "--odom-topic", path=path)
    elif request.odom is None:
        choices = cands.odometry_choices(ground_truth)
        if len(choices) == 1:
            odom = choices[0]
            notes.append(f"odometry: {odom} ({topics[odom]}; the only candidate; --odom-topic to choose another)")
        elif len(choices) > 1:
            raise RecorderError(
                f"several odometry candidates: {_listing(topics, choices, counts)}",
                path=path,
                fix="choose one with --odom-topic" + (" (and the ground truth with --ground-truth-topic)" if not ground_truth else ""),
            )
    if odom is not None and odom == ground_truth:
        raise RecorderError(f"{odom} is both the odometry and the ground truth", path=path, fix="choose two different topics")
    if left is None and odom is None and odom_tf is None:
        hint = f"--odom-from-tf {tf_hint[0]}:{tf_hint[1]}" if tf_hint else None
        if cands.tf:
            fix = f"pass {hint} (odometry from the TF tree)" if hint else "pass --odom-from-tf PARENT:CHILD"
        else:
            fix = "name a pose topic with --odom-topic, or image topics with --left-topic"
        raise RecorderError(
            "nothing to record: no images and no odometry topic"
            + (f" (pose topics: {_listing(topics, cands.poses, counts)})" if cands.poses else ""),
            path=path,
            fix=fix,
        )
    return TopicPlan(left=left, right=right, odom=odom, odom_from_tf=odom_tf, ground_truth=ground_truth,
                     ground_truth_from_tf=gt_tf, notes=tuple(notes))


def sibling_camera_info(image_topic: str, topics: Mapping[str, str]) -> str | None:
    """The ``camera_info`` topic next to an image topic (``/cam/left/image_raw`` -> ``/cam/left/camera_info``)."""
    base = image_topic.rsplit("/", 1)[0]
    for candidate in (f"{base}/camera_info", f"{base.rsplit('/', 1)[0]}/camera_info"):
        if topics.get(candidate) in CAMERA_INFO_TYPES:
            return candidate
    return None


# ---------------------------------------------------------------------------------------------
# ``lcv-replay info`` on a foreign log
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BagTopicInfo:
    """One topic: type, count, time span and mean rate (over the topic's own span)."""

    topic: str
    msgtype: str
    count: int
    first_ns: int
    last_ns: int
    serialization: str

    @property
    def rate_hz(self) -> float:
        span_s = (self.last_ns - self.first_ns) / 1e9
        return (self.count - 1) / span_s if self.count > 1 and span_s > 0 else 0.0


@dataclass(frozen=True)
class BagInfo:
    """What ``lcv-replay info`` prints for a foreign log (as ``ros2 bag info`` does, plus rates).

    ``start_ns``/``end_ns`` are the first and last message times (bag receive time).
    ``usable`` is one line on what lcv-replay could use, ``command`` the import command.
    """

    source: BagSource
    size_bytes: int
    ros_distro: str | None
    start_ns: int
    end_ns: int
    message_count: int
    topics: tuple[BagTopicInfo, ...]
    usable: str
    command: str | None
    problem: str | None = None
    tf_frames: tuple[str, ...] = ()
    tf_moving: tuple[str, ...] = ()  # "parent -> child (count)" of the /tf edges, most samples first
    tf_suggestion: tuple[str, str] | None = None

    @property
    def duration_s(self) -> float:
        return max(self.end_ns - self.start_ns, 0) / 1e9


def topic_times(reader: Any) -> dict[int, np.ndarray]:
    """Receive times (ns) of every message, per connection id, without deserialising anything.

    ROS 1 bags answer from their index; ROS 2 bags are read once (rosbags gives no index access).
    """
    times: dict[int, list[int] | np.ndarray] = {}
    if not reader.is2:
        for connection in reader.connections:
            index = connection.owner.indexes.get(connection.id, [])
            times[id(connection)] = np.fromiter((entry.time for entry in index), dtype=np.int64, count=len(index))
        return times  # type: ignore[return-value]
    lists: dict[int, list[int]] = {}
    for connection, stamp, _raw in reader.messages():
        lists.setdefault(id(connection), []).append(stamp)
    return {k: np.asarray(v, dtype=np.int64) for k, v in lists.items()}


def read_tf(reader: Any, source: BagSource, time_source: str = "auto") -> "Any":
    """A :class:`~recorders.tf_buffer.TfBuffer` with every transform of the bag's TF topics."""
    from recorders.tf_buffer import TfBuffer

    buffer = TfBuffer()
    connections = [c for c in reader.connections if c.msgtype in TF_TYPES and c.topic in TF_TOPICS]
    for connection, log_time, raw in reader.messages(connections=connections) if connections else ():
        add_tf_message(buffer, deserialize(reader, source, connection, log_time, raw), log_time,
                       static=is_static_tf_topic(connection.topic), time_source=time_source)
    return buffer


def add_tf_message(buffer: Any, message: Any, log_time_ns: int, *, static: bool, time_source: str) -> None:
    """Add every ``TransformStamped`` of a ``tf2_msgs/TFMessage`` to ``buffer``."""
    for tf in message.transforms:
        tr, rot = tf.transform.translation, tf.transform.rotation
        buffer.add(
            tf.header.frame_id, tf.child_frame_id, message_stamp_ns(tf, log_time_ns, time_source),
            (tr.x, tr.y, tr.z), (rot.x, rot.y, rot.z, rot.w), static=static,
        )


def message_stamp_ns(message: Any, log_time_ns: int, source: str) -> int:
    """A message's stamp: ``header.stamp`` (``"header"``), the bag time (``"log"``), or the header
    unless it is zero (``"auto"``)."""
    if source == "log":
        return int(log_time_ns)
    header = getattr(message, "header", None)
    stamp = 0 if header is None else int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
    if stamp == 0 and source == "auto":
        return int(log_time_ns)
    return stamp


def inspect_bag(paths: Sequence[str | Path]) -> BagInfo:
    """Open a foreign log and describe it (see :class:`BagInfo`)."""
    source = resolve_source(paths)
    with open_bag(source) as reader:
        times = topic_times(reader)
        per_topic: dict[str, list[Any]] = {}
        for connection in reader.connections:
            per_topic.setdefault(connection.topic, []).append(connection)
        topics = []
        for topic in sorted(per_topic):
            conns = per_topic[topic]
            stamps = np.concatenate([times.get(id(c), np.zeros(0, np.int64)) for c in conns]) if conns else np.zeros(0, np.int64)
            types = sorted({c.msgtype for c in conns})
            serialization = getattr(conns[0].ext, "serialization_format", "ros1") if source.kind == "ros2" else "ros1"
            topics.append(BagTopicInfo(
                topic, " | ".join(types), int(len(stamps)),
                int(stamps.min()) if len(stamps) else 0, int(stamps.max()) if len(stamps) else 0, serialization,
            ))
        all_stamps = [t for t in topics if t.count]
        start = min((t.first_ns for t in all_stamps), default=0)
        end = max((t.last_ns for t in all_stamps), default=0)
        type_of = {t.topic: t.msgtype for t in topics}
        counts = {t.topic: t.count for t in topics}
        tf = read_tf(reader, source) if any(type_of[t] in TF_TYPES for t in type_of) else None
        distro = None
        with contextlib.suppress(Exception):
            distro = reader.readers[0].ros_distro if source.kind == "ros2" else None
    hint = tf.suggest_odometry_pair() if tf is not None else None
    usable, command, problem = describe_usable(source, type_of, counts, hint)
    return BagInfo(
        source=source,
        size_bytes=source.size_bytes,
        ros_distro=distro,
        start_ns=start,
        end_ns=end,
        message_count=sum(t.count for t in topics),
        topics=tuple(topics),
        usable=usable,
        command=command,
        problem=problem,
        tf_frames=tuple(tf.frames) if tf is not None else (),
        tf_moving=tuple(f"{e.parent} -> {e.child} ({len(e.stamps_ns)})" for e in tf.dynamic_edges()) if tf is not None else (),
        tf_suggestion=hint,
    )


def inspect_mcap(container: Any, *, reason: str) -> BagInfo:
    """``info`` on an MCAP that is neither an lcv-replay log nor a ROS 2 bag (``reason``: why not ours).

    Uses the container index of :mod:`lcv_replay.log.container` (no chunk is decompressed).
    """
    path = Path(container.path)
    source = BagSource("mcap", "mcap", (path,), (path,), path.stem)
    topics = []
    for cid, channel in sorted(container.channels.items(), key=lambda item: item[1].topic):
        table = container.entries.get(cid)
        times = table["log_time"] if table is not None and len(table) else np.zeros(0, np.int64)
        schema = container.schemas.get(channel.schema_id)
        topics.append(BagTopicInfo(
            channel.topic, schema.name if schema is not None else "", int(len(times)),
            int(times.min()) if len(times) else 0, int(times.max()) if len(times) else 0, channel.message_encoding,
        ))
    counted = [t for t in topics if t.count]
    return BagInfo(
        source=source,
        size_bytes=int(container.file_size_bytes),
        ros_distro=None,
        start_ns=min((t.first_ns for t in counted), default=0),
        end_ns=max((t.last_ns for t in counted), default=0),
        message_count=sum(t.count for t in topics),
        topics=tuple(topics),
        usable=f"nothing: not an lcv-replay log ({reason}) and not a ROS 2 bag",
        command=None,
        problem=None,
    )


def describe_usable(
    source: BagSource, topics: Mapping[str, str], counts: Mapping[str, int], tf_hint: tuple[str, str] | None
) -> tuple[str, str | None, str | None]:
    """``(what lcv-replay could use, the record command, the problem if it cannot choose)``."""
    problem = None
    try:
        plan = pick_topics(topics, TopicRequest(), counts=counts, tf_hint=tf_hint)
    except RecorderError as exc:
        plan = _first_choice(topics, tf_hint)
        if plan is None:
            return "nothing lcv-replay can use (no images, no pose topic, no TF)", None, exc.message
        if plan.odom_from_tf is None or plan.left is not None:  # a real ambiguity, not just "odometry is on /tf"
            problem = exc.message + (f" ({exc.fix})" if exc.fix else "")
    parts, flags = [], []
    if plan.left and plan.right:
        parts.append(f"stereo pair on {plan.left} / {plan.right}")
        flags += ["--left-topic", plan.left, "--right-topic", plan.right]
    elif plan.left:
        parts.append(f"mono camera on {plan.left}")
        flags += ["--left-topic", plan.left]
    if plan.odom:
        parts.append(f"odometry on {plan.odom}")
        flags += ["--odom-topic", plan.odom]
    elif plan.odom_from_tf:
        parts.append(f"odometry from TF {plan.odom_from_tf[0]} -> {plan.odom_from_tf[1]}")
        flags += ["--odom-from-tf", f"{plan.odom_from_tf[0]}:{plan.odom_from_tf[1]}"]
    else:
        parts.append("no odometry")
    if plan.ground_truth:
        parts.append(f"ground truth on {plan.ground_truth}")
        flags += ["--ground-truth-topic", plan.ground_truth]
    quoted = " ".join(_shell_quote(str(p)) for p in source.paths)
    out = f"{source.name}.lcv.mcap"
    command = f"lcv-replay record rosbag {quoted} {' '.join(_shell_quote(f) for f in flags)} -o {_shell_quote(out)}".replace("  ", " ")
    return ", ".join(parts), command, problem


def _first_choice(topics: Mapping[str, str], tf_hint: tuple[str, str] | None) -> TopicPlan | None:
    """When :func:`pick_topics` cannot choose: the first candidate of each kind, for a suggestion."""
    cands = TopicCandidates.of(topics)
    left, right = (cands.stereo_pairs[0] if cands.stereo_pairs else (cands.images[0] if cands.images else None, None))
    gt = cands.ground_truth[0] if cands.ground_truth else None
    choices = cands.odometry_choices(gt)
    odom = choices[0] if choices else None
    odom_tf = tf_hint if odom is None and tf_hint else None
    if left is None and odom is None and odom_tf is None:
        return None
    return TopicPlan(left=left, right=right, odom=odom, odom_from_tf=odom_tf, ground_truth=gt)


def _shell_quote(text: str) -> str:
    import shlex

    return shlex.quote(text)


def format_bag_info(info: BagInfo) -> str:
    """``ros2 bag info`` text (files, size, storage, duration, start, end, messages, topics), with
    each topic's rate, then what lcv-replay could use and the command that imports it."""
    from lcv_replay.log.inspect import _size_text, _stamp_text  # the same figures as for our logs

    files = info.source.files
    lines = [
        f"Files:             {files[0].name}",
        *[f"                   {f.name}" for f in files[1:]],
        f"Bag size:          {_size_text(info.size_bytes)}",
        f"Storage id:        {info.source.storage}",
    ]
    if info.ros_distro:
        lines.append(f"ROS Distro:        {info.ros_distro}")
    lines += [
        f"Duration:          {info.duration_s:.9f}s",
        f"Start:             {_stamp_text(info.start_ns)}",
        f"End:               {_stamp_text(info.end_ns)}",
        f"Messages:          {info.message_count}",
    ]
    width = max((len(t.topic) for t in info.topics), default=0)
    type_width = max((len(t.msgtype) for t in info.topics), default=0)
    count_width = max((len(str(t.count)) for t in info.topics), default=1)
    for k, t in enumerate(info.topics):
        label = "Topic information: " if k == 0 else " " * 19
        lines.append(
            f"{label}Topic: {t.topic:<{width}} | Type: {t.msgtype:<{type_width}} | Count: {t.count:>{count_width}} | "
            f"Rate: {t.rate_hz:8.3f} Hz | Serialization Format: {t.serialization}"
        )
    if info.tf_frames:
        shown = ", ".join(info.tf_frames[:8]) + (f", ... ({len(info.tf_frames)} in all)" if len(info.tf_frames) > 8 else "")
        lines.append(f"TF frames:         {shown}")
        lines.append(f"TF moving:         {', '.join(info.tf_moving) or 'none (only /tf_static)'}")
    lines.append(f"lcv-replay could use: {info.usable}")
    if info.problem:
        lines.append(f"  to choose:       {info.problem}")
    if info.command:
        lines.append(f"  import:          {info.command}")
        lines.append(f"  or replay it:    lcv-replay {info.command.split(' rosbag ', 1)[1].rsplit(' -o ', 1)[0]}")
    return "\n".join(lines)


def bag_info_to_json(info: BagInfo) -> dict:
    """``lcv-replay info --json`` of a foreign log: the stable keys of our logs where they apply, plus the bag's."""
    return {
        "path": info.source.display,
        "format": info.source.kind,
        "storage": info.source.storage,
        "files": [str(f) for f in info.source.files],
        "file_size_bytes": info.size_bytes,
        "ros_distro": info.ros_distro,
        "duration_s": info.duration_s,
        "start_ns": info.start_ns,
        "end_ns": info.end_ns,
        "message_count": info.message_count,
        "topics": [
            {"topic": t.topic, "schema": t.msgtype, "count": t.count, "rate_hz": round(t.rate_hz, 6),
             "serialization_format": t.serialization}
            for t in info.topics
        ],
        "tf_frames": list(info.tf_frames),
        "tf_moving": list(info.tf_moving),
        "lcv_replay_can_use": info.usable,
        "lcv_replay_problem": info.problem,
        "record_command": info.command,
    }
