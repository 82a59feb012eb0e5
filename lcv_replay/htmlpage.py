"""Self-contained HTML pages: no script, no network fetch, figures inlined as base64 PNG.

Shared by every HTML output: the fleet pages (``fleet.html``, ``compare.html``) and the per-run
report (``lcv_replay.report.html``): one style, one way to escape, tabulate and embed a
matplotlib figure. The same input gives the same bytes (PNG metadata without a timestamp).
"""

from __future__ import annotations

import base64
import html
import io
from typing import Any, Iterable, Sequence

STYLE = """
body { font-family: system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; margin: 24px auto; max-width: 1200px;
       color: #1b1b1b; line-height: 1.4; padding: 0 16px; }
h1 { font-size: 22px; margin-bottom: 4px; } h2 { font-size: 18px; margin-top: 32px; border-bottom: 1px solid #ddd; }
.verdict { font-size: 16px; padding: 10px 14px; border-radius: 6px; background: #f2f6ff; border-left: 5px solid #3b6fd4; }
.verdict.bad { background: #fff1f0; border-left-color: #e0201e; } .verdict.good { background: #effaf1; border-left-color: #23b04a; }
table { border-collapse: collapse; font-size: 13px; margin: 8px 0; }
td, th { border: 1px solid #ddd; padding: 3px 8px; text-align: left; vertical-align: top; }
th { background: #f4f4f4; } td.num { text-align: right; font-variant-numeric: tabular-nums; }
tr.bad td { background: #fff1f0; } tr.good td { background: #f3fbf4; } tr.muted td { color: #777; } td.why { color: #555; }
figure { margin: 12px 0; } figure img { max-width: 100%; border: 1px solid #eee; }
figcaption { font-size: 13px; color: #444; } code { background: #f4f4f4; padding: 0 3px; }
details summary { cursor: pointer; color: #3b6fd4; } .muted { color: #777; }
"""


class Raw(str):
    """Trusted HTML (a link built here), inserted into a table cell as is."""


def esc(value: Any) -> str:
    """HTML-escaped text of ``value`` (a :class:`Raw` passes through)."""
    if isinstance(value, Raw):
        return str(value)
    return html.escape(str(value), quote=True)


def num(value: Any, fmt: str = ".3f", *, none: str = "n/a") -> str:
    """A figure for a table: floats with ``fmt``, ``None`` as ``none``, anything else as text."""
    if value is None:
        return none
    if isinstance(value, float):
        return format(value, fmt)
    return str(value)


def link(href: str, text: str) -> Raw:
    return Raw(f'<a href="{html.escape(href, quote=True)}">{html.escape(text)}</a>')


def table(header: Sequence[str], rows: Iterable[Sequence[Any]], *, numeric: Sequence[bool] | None = None,
          row_classes: Sequence[str] | None = None) -> str:
    """An HTML table; ``numeric[i]`` right-aligns column ``i``; ``row_classes[k]`` styles row ``k``
    (``bad``, ``good``, ``muted``)."""
    out = ["<table><tr>" + "".join(f"<th>{esc(h)}</th>" for h in header) + "</tr>"]
    for k, row in enumerate(rows):
        cls = row_classes[k] if row_classes and k < len(row_classes) and row_classes[k] else ""
        cells = []
        for i, value in enumerate(row):
            td = ' class="num"' if numeric and i < len(numeric) and numeric[i] else ""
            cells.append(f"<td{td}>{esc(value)}</td>")
        out.append((f'<tr class="{cls}">' if cls else "<tr>") + "".join(cells) + "</tr>")
    out.append("</table>")
    return "".join(out)


def png_bytes(fig: Any, *, dpi: int = 100) -> bytes:
    """A matplotlib figure as PNG bytes (no timestamp in the metadata: the same figure, the same bytes)."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi, metadata={"Software": None}, bbox_inches="tight")
    return buffer.getvalue()


def figure(png: bytes | None, alt: str, caption: str) -> str:
    """An inlined figure, or a line saying there is nothing to draw."""
    if png is None:
        return f'<p class="muted">{esc(alt)}: nothing to draw.</p>'
    data = base64.b64encode(png).decode("ascii")
    return f'<figure><img alt="{esc(alt)}" src="data:image/png;base64,{data}"><figcaption>{esc(caption)}</figcaption></figure>'


def page(title: str, body: str) -> str:
    """A whole HTML document around ``body``."""
    return (
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
        f"<title>{esc(title)}</title><style>{STYLE}</style></head><body>\n{body}\n</body></html>\n"
    )
