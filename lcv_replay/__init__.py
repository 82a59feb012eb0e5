"""lcv-replay: replay robot logs through place recognition and incremental loop-closure verification."""

__version__ = "0.1.0"
