"""The cost model's admission (pipelines.cost): a session whose options could not fit one epoch in the CPU
budget per batch is refused at creation, and a batch with too many measurements in an epoch or predicted to
cost more than the budget is refused before it runs (422, naming what to send instead)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from edgepos.api.errors import ApiError
from edgepos.api.schemas import ProblemModel
from edgepos.pipelines import cost


def too_heavy_options(pipeline: str, options: Mapping[str, Any], epoch_s: float, budget_s: float) -> str:
    """Why a session with these options is refused at creation: one epoch of the most measurements a batch
    may carry costs ``epoch_s`` (s), over the ``budget_s`` per batch; with what to choose instead."""
    counts = ", ".join(f"{count} {kind}" for kind, count in cost.MAX_PER_EPOCH[pipeline].items())
    reason = (
        f"one epoch of the most measurements a batch may carry ({counts}) would cost about "
        f"{epoch_s * 1e3:.0f} ms of CPU under these options, over the server's budget of {budget_s * 1e3:g} ms "
        "per batch (EDGEPOS_BATCH_CPU_BUDGET_MS)"
    )
    if pipeline == "gnss_tight" and options.get("filter") in ("pf", "upf"):
        most = cost.max_particles(str(options["filter"]), budget_s)
        reason += f"; with filter {options['filter']!r} use at most {most} particles"
    else:
        reason += "; choose a lighter filter or fewer motion models"
    return reason


def admit_batch(
    budget_s: float,
    pipeline: str,
    options: Mapping[str, Any],
    observations: list[Any],
    replayed: list[Any] | None = None,
) -> float:
    """The batch's predicted CPU seconds (with the stored observations a late measurement makes the lag
    window filter again), after refusing (422) an epoch with more measurements of a kind than the
    pipeline accepts per epoch, or a batch predicted to cost more than the budget."""
    predicted, violations = cost.admit(pipeline, options, observations)
    if replayed:
        predicted += cost.batch_cost_s(pipeline, options, replayed)
    if violations:
        problems = [ProblemModel(index=None, field="measurements", reason=v.reason) for v in violations[:20]]
        raise ApiError(
            "invalid_request",
            "the batch has epochs with too many measurements; the session is unchanged",
            problems,
        )
    if predicted > budget_s:
        epochs = len({o.t for o in observations} | {o.t for o in replayed or ()})
        fit = int(budget_s / (predicted / epochs)) if epochs else 0
        again = (
            f", {len({o.t for o in replayed})} of them filtered again for late measurements"
            if replayed
            else ""
        )
        advice = (
            f"send at most about {fit} epochs like these per batch"
            if fit >= 1
            else "one epoch like these alone is over it: send fewer measurements per epoch, or open a session with "
            "cheaper options (fewer particles; for gnss_tight also use_doppler false: each Doppler adds a row to "
            "the update)"
        )
        reason = (
            f"this batch would cost about {predicted * 1e3:.0f} ms of CPU ({epochs} epochs{again}), over the server's "
            f"budget of {budget_s * 1e3:g} ms per batch (EDGEPOS_BATCH_CPU_BUDGET_MS): {advice}"
        )
        raise ApiError(
            "invalid_request",
            "the batch is too costly to filter at once; the session is unchanged",
            [ProblemModel(index=None, field="measurements", reason=reason)],
        )
    return predicted
