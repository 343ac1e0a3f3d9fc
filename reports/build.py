"""Assemble ``report.md``, ``report.html`` and ``figures/*.png`` from a saved results folder."""

from __future__ import annotations

from pathlib import Path

from .figures import (FIG_DIR, FigureOut, fisher_figure, headline_figure, model_colors, rollout_figure,
                      solve_time_figure, trajectory_figures)
from .headline import correlation_text, headline_data
from .html import markdown_to_html
from .sections.identification import highfi_table, table_six
from .sections.plants import plants_section, split_by_plant, where_sentence
from .sections.realflights import realdata_section
from .inputs import load_inputs
from .sections.summary import summary_text
from .sections.learn import learn_section
from .sections.levels import levels_section
from .sections.versus import versus_section
from .sections.estimation import estimation_section, split_by_estimator
from .sections.zoo import (NO_STUDY, answer_text, dose_response_figure, estimator_threshold_section, max_speed_figure,
                           predictor_table, provenance_text, zoo_table)
from .tables import (closed_loop_table, ensemble_table, fisher_table, hover_table, ladder_table, provenance_section,
                     realtime_table, solve_time_table, table_one, table_three, table_two)

#: Title of the report (the Markdown ``#`` heading and the HTML title).
TITLE = "pinn-mpc report"
#: Section headings of the report, in order (Markdown ``##``, HTML ``<h2>``).
SECTIONS = (
    "Dose-response: open-loop error against closed-loop failure",
    "Maximum trackable speed of the zoo",
    "Which open-loop number predicts failure",
    "The model zoo",
    "Dose-response with the state estimator",
    "Summary",
    "Table I: one-step and 100-step accuracy",
    "Table II: parameter identification and Cramér-Rao bounds",
    "Table III: ablation",
    "Table VI: identification under model mismatch",
    "Closed-loop results",
    "High-fidelity plant: models trained on its own data",
    "Learned against nominal on plants with unmodelled physics",
    "Command levels: wrench, ctbr and ctatt side by side",
    "Learning from flown flights",
    "Other plants and vehicles",
    "Real flights: the nano-drone benchmark",
    "State estimation and offset-free control",
    "Hover: settled error and gust recovery",
    "Speed ladder: maximum trackable speed",
    "Ensembles: crash probability and RMSE with intervals",
    "Real-time timing: compute time charged",
    "Headline: open-loop error against closed-loop error",
    "Trajectories and tracking error",
    "Rollout error growth",
    "Fisher information spectrum",
    "Solve time",
    "Provenance",
)


def _figure_md(f: FigureOut) -> str:
    return f"![{f.alt}]({f.path})\n\n{f.caption}"


def _clear_figures(run_dir: Path) -> None:
    """Remove the PNG files of an earlier build so that none is left stale."""
    d = run_dir / FIG_DIR
    if d.is_dir():
        for p in sorted(d.glob("*.png")):
            p.unlink()


def _zoo_sections(study, d: Path, body: dict) -> None:
    """The report's lead: the zoo study's answer, figures and tables (or how to produce them)."""
    names = ("Dose-response: open-loop error against closed-loop failure", "Maximum trackable speed of the zoo",
             "Which open-loop number predicts failure", "The model zoo")
    if study is None:
        for n in names:
            body[n] = NO_STUDY
        return
    f = dose_response_figure(study, d)
    body[names[0]] = "\n\n".join([provenance_text(study), answer_text(study)] + ([_figure_md(f)] if f else []))
    f = max_speed_figure(study, d)
    body[names[1]] = _figure_md(f) if f else "The study has no model."
    body[names[2]] = predictor_table(study)
    body[names[3]] = zoo_table(study)


def report_markdown(run_dir) -> str:
    """Read ``run_dir``, write its figures and return the report as Markdown.

    Parameters
    ----------
    run_dir : str or Path
        Results folder (see :mod:`reports.inputs` for the files read).

    Raises
    ------
    ReportError
        A required file is missing or malformed.
    """
    inp = load_inputs(run_dir)
    d = inp.run_dir
    _clear_figures(d)
    # Every section but the one on other plants reads the runs on the folder's own plant and vehicle.
    inp.runs, other_plants = split_by_plant(inp.runs, inp.plan)
    members = [r for r in inp.runs if r.get("member") is not None]
    every_run = [r for r in inp.runs if r.get("member") is None]
    # Every section but the real-time one reads the ideal-timing runs (results without a timing are ideal); the
    # ensembles' members have their own section, every other table has one run per case.
    inp.runs = [r for r in every_run if r.get("timing", "ideal") == "ideal"]
    # Runs with the state estimator have their own section; every other one reads the runs without (or, in a folder
    # flown with the estimator throughout, those with it).
    without, estimated = split_by_estimator(inp.runs)
    if without:
        inp.runs, every_run = without, split_by_estimator(every_run)[0]
    head = headline_data(inp.runs, inp.models_by_name())
    corr = correlation_text(head)
    body = {}
    _zoo_sections(inp.study, d, body)
    body["Dose-response with the state estimator"] = estimator_threshold_section(inp.study, inp.study_ekf)
    body["Summary"] = summary_text(inp.runs, corr if head.points else None)
    body["Table I: one-step and 100-step accuracy"] = table_one(inp.evaluation)
    body["Table II: parameter identification and Cramér-Rao bounds"] = (
        table_two(inp.evaluation) + "\n\n" + fisher_table(inp.fisher))
    body["Table III: ablation"] = table_three(inp.ablation, inp.evaluation)
    body["Table VI: identification under model mismatch"] = table_six(inp.evaluation)
    body["Closed-loop results"] = (where_sentence(inp.runs) + (" " if inp.runs else "")
                                   + closed_loop_table(inp.runs))
    body["High-fidelity plant: models trained on its own data"] = highfi_table(
        inp.runs + members, inp.evaluation)
    body["Learned against nominal on plants with unmodelled physics"] = versus_section(inp.versus)
    body["Command levels: wrench, ctbr and ctatt side by side"] = "\n\n".join(
        [levels_section(inp.levels)] + [f"**Learned against nominal at the `{lv}` level**\n\n" + versus_section(v)
                                        for lv, v in inp.versus_levels.items()])
    body["Learning from flown flights"] = learn_section(inp.learn, d, _figure_md)
    body["Other plants and vehicles"] = plants_section(inp.runs, other_plants)
    body["Real flights: the nano-drone benchmark"] = realdata_section(inp.realdata)
    body["State estimation and offset-free control"] = estimation_section(without, estimated)
    body["Hover: settled error and gust recovery"] = hover_table(inp.runs)
    body["Speed ladder: maximum trackable speed"] = ladder_table(inp.runs)
    body["Ensembles: crash probability and RMSE with intervals"] = ensemble_table(members)
    body["Real-time timing: compute time charged"] = realtime_table(every_run)
    f = headline_figure(head, d)
    body["Headline: open-loop error against closed-loop error"] = (
        _figure_md(f) + "\n\n" + corr if f is not None else
        "No closed-loop run of a learned model listed in `evaluation.json` has an RMSE, so there is no "
        "headline figure." + (f" Models flown but not in `evaluation.json`: {', '.join(head.unmatched)}."
                              if head.unmatched else ""))
    colors = model_colors([r["model"] for r in inp.runs] + list(inp.models_by_name()))
    figs, notes = trajectory_figures(inp, d, colors)
    body["Trajectories and tracking error"] = "\n\n".join([_figure_md(f) for f in figs] + notes)
    f = rollout_figure(inp.evaluation, d, colors)
    body["Rollout error growth"] = (_figure_md(f) if f is not None else
                                    "`evaluation.json` holds no per-step rollout errors (`position_by_step`).")
    f = fisher_figure(inp.fisher, d)
    body["Fisher information spectrum"] = (_figure_md(f) if f is not None else
                                           "`fisher.json` holds no eigenvalues.")
    f = solve_time_figure(inp.runs, d)
    body["Solve time"] = ((_figure_md(f) + "\n\n" if f is not None else "") + solve_time_table(inp.runs))
    body["Provenance"] = provenance_section(inp.provenance, inp.plan)
    parts = [f"# {TITLE}", f"Results folder: `{d.name}`. Generated from the saved files in it."]
    parts += [f"## {s}\n\n{body[s].strip()}" for s in SECTIONS]
    return "\n\n".join(parts) + "\n"


def build_report(run_dir) -> Path:
    """Build ``report.md``, ``report.html`` and ``figures/*.png`` in ``run_dir``.

    Works from the saved files alone (``pinnmpc report DIR`` rebuilds a
    report). Deterministic: the same files give the same outputs.

    Parameters
    ----------
    run_dir : str or Path
        Results folder with ``results.json``, ``evaluation.json`` and
        ``fisher.json`` (required), and ``ablation.json``, ``provenance.json``,
        ``study.json``, ``traces/*.npz`` (optional).

    Returns
    -------
    Path
        Path of the written ``report.md``.

    Raises
    ------
    ReportError
        (a ``ValueError``) A required file is missing or malformed; the
        message names it.
    """
    d = Path(run_dir)
    md = report_markdown(d)
    page = markdown_to_html(md, d, TITLE)
    out = d / "report.md"
    out.write_text(md, encoding="utf-8")
    (d / "report.html").write_text(page, encoding="utf-8")
    return out
