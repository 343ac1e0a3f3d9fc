"""The report's section on real flight logs (``realdata.json`` of ``pinnmpc realdata``)."""

from __future__ import annotations

#: Shown when the results folder has no realdata.json.
NO_REALDATA = ("No `realdata.json` in this folder. `pinnmpc realdata --logs BENCH --out DIR`, with `DIR` this folder "
               "and `BENCH` a clone of the nano-drone identification benchmark, imports its real flights, trains and "
               "evaluates every model under the benchmark's protocol, flies the best flyable one, and writes it "
               "(docs/real-flights.md); `pinnmpc report DIR` then shows it here.")


def realdata_section(realdata: dict | None) -> str:
    """Markdown: the study's tables (the published rows beside ours) with their headings one level down."""
    if realdata is None:
        return NO_REALDATA
    from scenarios.studies.realdata import realdata_markdown

    lines = realdata_markdown(realdata).splitlines()
    body = [("#" + line if line.startswith("## ") else line) for line in lines if not line.startswith("# ")]
    return "\n".join(body).strip()
