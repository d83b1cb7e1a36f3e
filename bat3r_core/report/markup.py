"""HTML pieces of the report: section titles and ids, embedded PNG figures, tables, notes, the page's CSS."""
from __future__ import annotations

import base64
import html
import io
import math
from typing import Sequence

from matplotlib.figure import Figure


SECTION_IDS = ("summary", "metrics-over-iterations", "ablation-table", "collection-masks", "per-cluster",
               "failure-rates",
               "camera-distribution", "angle-fits", "pseudo-labels", "qualitative")
_TITLES = {
    "summary": "Run summary",
    "metrics-over-iterations": "Metrics across iterations",
    "ablation-table": "Ablation-style table",
    "collection-masks": "Collection mask IoU (no 3D ground truth)",
    "per-cluster": "Per-cluster mCD",
    "failure-rates": "Failure rates: azimuth × pose complexity",
    "camera-distribution": "Camera distribution",
    "angle-fits": "Student's t vs Normal fits of camera angles",
    "pseudo-labels": "Pseudo-label quality",
    "qualitative": "Qualitative results",
}

def _png(fig: Figure, alt: str) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    data = base64.b64encode(buf.getvalue()).decode("ascii")
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'


def _note(text: str) -> str:
    return f'<p class="na">{html.escape(text)}</p>'


def _fmt(v, digits: int = 2) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return html.escape(str(v))


def _table(header: Sequence[str], rows: Sequence[Sequence], cls: str = "") -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{_fmt(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f'<table class="{cls}"><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>'


_CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0;color:#222;background:#f6f7f9}
header{background:#243447;color:#fff;padding:16px 32px}header h1{margin:0;font-size:22px}
header p{margin:4px 0 0;color:#c9d3de;font-size:13px}
nav{position:sticky;top:0;background:#fff;border-bottom:1px solid #dde;padding:8px 32px;z-index:1;font-size:13px}
nav a{margin-right:14px;color:#245;text-decoration:none}nav a:hover{text-decoration:underline}
main{padding:8px 32px 40px;max-width:1500px}
section{background:#fff;border:1px solid #e2e5ea;border-radius:6px;margin:16px 0;padding:12px 20px}
section h2{font-size:18px;margin:4px 0 10px;color:#243447}h3{font-size:15px;margin:14px 0 6px}
img{max-width:100%;height:auto;display:block;margin:6px 0}
table{border-collapse:collapse;font-size:13px;margin:6px 0}th,td{padding:4px 10px;border-bottom:1px solid #e6e8ec}
th{background:#f0f2f5;text-align:left}table.num td{text-align:right}table.num td:first-child{text-align:left}
.na{color:#8a6d00;background:#fff8e0;border-left:4px solid #f0c040;padding:6px 10px}
.error{color:#9b1c1c;background:#fdecec;border-left:4px solid #d33;padding:6px 10px}
.caption{color:#555;font-size:12px}.headline{font-size:15px}code{font-size:12px}
"""
