"""The RSU + IMU evaluation's outputs: the table beside the paper's Tables 2 and 4, the derived
comparisons, the --json document and the figures (cf. Figs. 6-7 and 10-13)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from edgepos.eval import plots
from edgepos.eval.integrity import stanford_plot
from edgepos.eval.rsu_imu_algorithms import AVERAGE_SUFFIX, IMM_VARIANTS, PAPER, SINGLE_MODELS
from edgepos.eval.rsu_imu_late import LateSettings
from edgepos.eval.rsu_imu_montecarlo import Result
from edgepos.eval.tables import format_table, number, percent_change
from edgepos.sim.scenarios import Scenario


def timing_note(workers: int) -> str:
    """Why the time per step here is not the benchmark figure."""
    cores = os.cpu_count() or 1
    return (
        "Time per step is the wall time of pipeline.process over a run / its epochs, measured inside the "
        f"Monte Carlo with {workers} worker process(es) on {cores} core(s) all busy: it is not the benchmark "
        "figure (see bench/)."
    )


def paper_note() -> str:
    """How to read the paper's columns."""
    return (
        "The paper ran one filter per RSU and averaged the estimates, so its figures belong beside the "
        "/avg rows; on joint rows (all RSUs in one update) they are shown in parentheses for reference only. "
        "Paper times are from its own machine."
    )


def results_table(results_by_name: dict[str, Result]) -> str:
    """Tables 2 and 4 side by side with ours."""
    headers = [
        "algorithm",
        "pos RMSE (m)",
        "vel RMSE (m/s)",
        "step (us)",
        "paper pos (m)",
        "paper vel (m/s)",
        "paper step (us)",
    ]
    rows = []
    for result in results_by_name.values():
        paper = result.algorithm.paper
        algorithm = result.algorithm
        cells = [algorithm.name, number(result.pos_mean, 4), number(result.vel_mean, 4)]
        cells.append(number(result.step_us, 1))
        if paper is None:
            cells += ["-", "-", "-"]
        else:
            values = [number(paper.pos_rmse_m, 4), number(paper.vel_rmse_mps, 4), number(paper.step_us, 1)]
            if algorithm.handling != "average":
                values = [f"({value})" for value in values]
            cells += values
        rows.append(cells)
    return format_table(headers, rows, right=[False] + [True] * 6)


def _comparison_rows(results_by_name: dict[str, Result]) -> list[list[str]]:
    rows = []

    def add(label: str, handling: str, reference: str, candidate: str, paper: tuple[str, str] | None) -> None:
        """A row: how much lower ``candidate``'s mean RMSE is than ``reference``'s, and the paper's."""
        if reference not in results_by_name or candidate not in results_by_name:
            return
        ref, cand = results_by_name[reference], results_by_name[candidate]
        paper_cells = ["-", "-"]
        if paper is not None:
            paper_ref, paper_cand = PAPER[paper[0]], PAPER[paper[1]]
            paper_cells = [
                number(percent_change(paper_ref.pos_rmse_m, paper_cand.pos_rmse_m), 1),
                number(percent_change(paper_ref.vel_rmse_mps, paper_cand.vel_rmse_mps), 1),
            ]
        rows.append(
            [
                label,
                handling,
                number(percent_change(ref.pos_mean, cand.pos_mean), 1),
                number(percent_change(ref.vel_mean, cand.vel_mean), 1),
                *paper_cells,
            ]
        )

    paper_best_single = min(SINGLE_MODELS, key=lambda name: PAPER[name].pos_rmse_m)
    for handling, suffix in (("joint", ""), ("average", AVERAGE_SUFFIX)):
        for other in ("IMM-CKF", "IMM-UKF", "IMM-EKF"):
            add(f"2IMM-CKF vs {other}", handling, other + suffix, "2IMM-CKF" + suffix, (other, "2IMM-CKF"))
        singles = [name + suffix for name in SINGLE_MODELS if name + suffix in results_by_name]
        if singles:
            best = min(singles, key=lambda name: results_by_name[name].pos_mean)
            for variant in IMM_VARIANTS:
                best_base = results_by_name[best].algorithm.base
                label = f"{variant} vs best single ({best_base}; paper {paper_best_single})"
                add(label, handling, best, variant + suffix, (paper_best_single, variant))
    for base in [*SINGLE_MODELS, *IMM_VARIANTS]:
        add(f"{base}: joint vs average", "-", base + AVERAGE_SUFFIX, base, None)
    return rows


def comparisons_table(results_by_name: dict[str, Result]) -> str | None:
    """The derived comparisons: percent lower mean RMSE of the candidate than the reference."""
    rows = _comparison_rows(results_by_name)
    if not rows:
        return None
    headers = ["comparison (candidate vs reference)", "handling", "pos %", "vel %"]
    headers += ["paper pos %", "paper vel %"]
    return format_table(headers, rows, right=[False, False, True, True, True, True])


def late_table(results_by_name: dict[str, Result], late: LateSettings) -> str | None:
    """Smoothed RMSE beside the filtered one; with late delivery the last fix per epoch beside the in-order
    run and beside dropping the late measurements."""
    rows = []
    for name, r in results_by_name.items():
        if not r.extra:
            continue
        cells = [name, number(r.pos_mean, 4)]
        if "smooth_pos" in r.extra:
            cells += [
                number(r.extra["smooth_pos"], 4),
                number(percent_change(r.pos_mean, r.extra["smooth_pos"]), 1),
            ]
        if "late_pos" in r.extra:
            cells += [
                number(r.extra["late_pos"], 4),
                number(r.extra["late_pos"] / r.pos_mean, 4),
                number(r.extra["drop_pos"], 4),
                number(r.extra["drop_pos"] / r.pos_mean, 4),
            ]
        rows.append(cells)
    if not rows:
        return None
    headers = ["algorithm", "filtered pos (m)"]
    if late.smooth_lag_s is not None:
        headers += [f"smoothed, lag {late.smooth_lag_s:g} s (m)", "lower by %"]
    if late.delivery is not None:
        headers += ["late: last fix (m)", "x in-order", "dropped (m)", "x in-order"]
    return format_table(headers, rows, right=[False] + [True] * (len(headers) - 1))


def late_note(late: LateSettings) -> str | None:
    delivery = late.delivery
    if delivery is None:
        return None
    return (
        f"Late delivery: {delivery.fraction:.0%} of the RSU measurements arrive {delivery.min_delay_s:g}-"
        f"{delivery.max_delay_s:g} s late (uniform); the vehicle sends a batch every {late.batch_epochs} "
        "epoch(s); 'late' keeps the last fix received per epoch (revised fixes replace earlier ones, session "
        "option max_delay_s at its default), 'dropped' discards every measurement that missed its epoch's batch."
    )


def report(
    results_by_name: dict[str, Result], runs: int, seed: int, workers: int, late: LateSettings | None = None
) -> str:
    """The whole text report."""
    parts = [
        (
            f"RSU + IMU paper scenario (sec. 5): {runs} Monte Carlo run(s), seed {seed}; "
            "mean over time steps of the RMSE over runs (eqs. 39-40)."
        ),
        "",
        results_table(results_by_name),
        "",
        "Note: " + paper_note(),
        "Note: " + timing_note(workers),
    ]
    extra = None if late is None else late_table(results_by_name, late)
    if extra is not None and late is not None:
        parts += ["", "Smoothing and late measurements, mean position RMSE:", "", extra]
        note = late_note(late)
        if note:
            parts += ["Note: " + note]
    parts += [
        "",
        "Integrity (protection levels against the truth; docs/integrity.md):",
        "",
        integrity_table(results_by_name),
    ]
    comparisons = comparisons_table(results_by_name)
    if comparisons is not None:
        parts += [
            "",
            (
                "Improvement in mean RMSE, percent (positive: the candidate's error is lower than the "
                "reference's):"
            ),
            "",
            comparisons,
        ]
    return "\n".join(parts)


def to_json(
    results_by_name: dict[str, Result],
    scenario: Scenario,
    runs: int,
    seed: int,
    workers: int,
    late: LateSettings | None = None,
) -> dict[str, Any]:
    """The --json document (``*_rmse_m``/``_mps`` of the smoothing and late columns when run)."""
    notes = [paper_note(), timing_note(workers)]
    note = None if late is None else late_note(late)
    if note:
        notes.append(note)
    return {
        "scenario": scenario.name,
        "runs": runs,
        "seed": seed,
        "algorithms": {
            name: {
                "pos_rmse_m": r.pos_mean,
                "vel_rmse_mps": r.vel_mean,
                "step_us": r.step_us,
                **{
                    f"{column}_rmse_{'m' if column.endswith('pos') else 'mps'}": value
                    for column, value in r.extra.items()
                },
                "integrity": r.integrity.summary(r.algorithm_alert_limit),
            }
            for name, r in results_by_name.items()
        },
        "notes": notes,
    }


def integrity_table(results_by_name: dict[str, Result]) -> str:
    """Availability, misleading and hazardous epochs, median protection level and detections per algorithm."""
    rows = []
    for name, r in results_by_name.items():
        summary = r.integrity.summary(r.algorithm_alert_limit)
        detected = (
            f"{summary['detected_runs']} of {summary['faulty_runs']}" if summary["faulty_runs"] else "-"
        )
        delay = summary["mean_detection_delay_s"]
        rows.append(
            [
                name,
                f"{summary['availability']:.4f}",
                f"{summary['misleading']}",
                f"{summary['hazardous']}",
                "-"
                if summary["median_protection_level_m"] is None
                else f"{summary['median_protection_level_m']:.3f}",
                f"{summary['detections']} ({summary['false_exclusions']} false)",
                detected,
                "-" if delay is None else f"{delay:.2f}",
            ]
        )
    header = [
        "algorithm",
        "availability",
        "misleading",
        "hazardous",
        "median PL (m)",
        "exclusions",
        "faulty runs detected",
        "mean delay (s)",
    ]
    return format_table(header, rows)


def write_plots(results_by_name: dict[str, Result], scenario: Scenario, directory: Path) -> list[Path]:
    """Figs. 6-7 and 10-13 of the paper, once for joint and once for average RSU handling; figures whose
    algorithms were not run are skipped."""
    t = scenario.truth.t[1:]
    written = []
    for handling, suffix, tag in (("joint", "", "joint"), ("average", AVERAGE_SUFFIX, "avg")):
        chosen = {name: r for name, r in results_by_name.items() if r.algorithm.handling == handling}
        groups = (("single", "6-7", "single-model CKFs"), ("imm", "10-11", "IMM variants"))
        for group, figures, label in groups:
            members = {r.algorithm.base: r for r in chosen.values() if r.algorithm.group == group}
            if not members:
                continue
            fig_pos, fig_vel = figures.split("-")
            for quantity, unit, attribute, fig in (
                ("position", "m", "pos_rmse", fig_pos),
                ("velocity", "m/s", "vel_rmse", fig_vel),
            ):
                series = {base: getattr(r, attribute) for base, r in members.items()}
                written.append(
                    plots.line_plot(
                        directory / f"{quantity}_rmse_{group}_{tag}.png",
                        t,
                        series,
                        f"{quantity.capitalize()} RMSE, {label}, RSU handling {handling} (cf. paper Fig. {fig})",
                        f"{quantity} RMSE ({unit})",
                        plots.readable_ylim(series),
                    )
                )
        for base, fig in (("IMM-CKF", "12"), ("2IMM-CKF", "13")):
            result = results_by_name.get(base + suffix)
            if result is None or result.probabilities is None:
                continue
            models = result.algorithm.options["models"]
            labels = [model.upper() if model != "singer" else "Singer" for model in models]
            series = {label: result.probabilities[:, j] for j, label in enumerate(labels)}
            written.append(
                plots.line_plot(
                    directory / f"model_probabilities_{base.lower().replace('-', '_')}_{tag}.png",
                    t,
                    series,
                    f"Model probabilities, {base}, RSU handling {handling} (cf. paper Fig. {fig})",
                    "mean model probability",
                    (0.0, 1.0),
                )
            )
    for name, result in results_by_name.items():
        if result.integrity.count("epochs"):
            written.append(
                stanford_plot(
                    result.integrity,
                    result.algorithm_alert_limit,
                    f"Stanford diagram, {name}",
                    directory
                    / f"stanford_{name.lower().replace('-', '_').replace('/', '_').replace(' ', '_')}.png",
                )
            )
    return written
