"""Report generation: tables and figures from a saved results folder.

``build_report(run_dir)`` reads ``results.json``, ``evaluation.json``,
``fisher.json`` (required) and ``ablation.json``, ``provenance.json``,
``traces/*.npz`` (optional) and writes ``report.md``, a self-contained
``report.html`` and ``figures/*.png``. Nothing here imports torch.
"""

import sim  # noqa: F401  (first: it pins the BLAS kernel before numpy loads)

from .build import build_report
from .errors import ReportError

__all__ = ["build_report", "ReportError"]
