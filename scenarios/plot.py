"""The figure of one run (``pinnmpc fly --plot``): path, height, position error, inputs."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def plot_run(result: dict, trace: dict, path) -> Path:
    """Write a 2 x 2 PNG of one closed-loop run to ``path``; returns the path.

    Panels: horizontal path (east y against north x, m) with the reference;
    height ``h = -z`` (m) against time (s); position error (m) against time;
    thrust (N) against time. A crash is marked.
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .closed_loop.metrics import position_errors

    path = Path(path)
    t, x, r = trace["t"], trace["x"], trace["x_ref"]
    fig, ax = plt.subplots(2, 2, figsize=(10, 7.5))
    a = ax[0, 0]
    a.plot(r[:, 1], r[:, 0], "k--", lw=1, label="reference")
    a.plot(x[:, 1], x[:, 0], lw=1.5, label="flown")
    a.plot(x[0, 1], x[0, 0], "o", color="tab:green", label="start")
    a.set_xlabel("east y (m)")
    a.set_ylabel("north x (m)")
    a.set_aspect("equal", adjustable="datalim")
    a.set_title("horizontal path")
    a = ax[0, 1]
    a.plot(t, -r[:, 2], "k--", lw=1, label="reference")
    a.plot(t, -x[:, 2], lw=1.5, label="flown")
    a.set_xlabel("time (s)")
    a.set_ylabel("height h = -z (m)")
    a.set_title("height")
    a = ax[1, 0]
    with np.errstate(invalid="ignore"):
        e = position_errors(x, r)
    a.semilogy(t, np.maximum(e, 1e-5), lw=1.2)
    a.set_xlabel("time (s)")
    a.set_ylabel("position error (m)")
    a.set_title("tracking error")
    a = ax[1, 1]
    if len(trace["u"]):
        a.step(t[:-1], trace["u"][:, 0], where="post", lw=1.2, label="thrust T applied")
    a.set_xlabel("time (s)")
    a.set_ylabel("thrust (N)")
    a.set_title("collective thrust")
    if result.get("crashed"):
        for a in (ax[0, 1], ax[1, 0], ax[1, 1]):
            a.axvline(result["crash_time_s"], color="tab:red", lw=1, label=f"crash: {result['crash_reason']}")
    for a in ax.ravel():
        a.grid(True, alpha=0.3)
        if a.get_legend_handles_labels()[0]:
            a.legend(fontsize=8, loc="best")
    rmse = result.get("rmse_position_m")
    fig.suptitle(f"{result['scenario']} | {result['controller']} | {result['model']} | "
                 f"RMSE {rmse:.3g} m" if rmse is not None else f"{result['scenario']} | {result['controller']}")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
