"""Benchmark: one 2IMM-CKF step (models CA, AT, Singer; 4 RSUs + gyro) beside a plain transcription.

Prints the median and 90th percentile of the project's bank step (interaction, prediction, joint
update, 2IMM output), of the rsu_imu pipeline per epoch (adds RSU selection, gating and the fix),
and of the model-by-model transcription in ``baseline_2imm_ckf.py``, timed interleaved in the same
run so that load on the machine hits all alike; then checks that project and baseline agree.

    python bench/filter_step.py [--iterations N]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import baseline_2imm_ckf  # noqa: E402

from edgepos.core.measurements import GyroYawRate, RsuRangeBearing, Stacked  # noqa: E402
from edgepos.core.updates import JointCorrection  # noqa: E402
from edgepos.pipelines.base import InitialState  # noqa: E402
from edgepos.pipelines.registry import get_pipeline  # noqa: E402
from edgepos.pipelines.rsu_imu import _bank, _decode, _options_key  # noqa: E402
from edgepos.sim.scenarios import rsu_imu_paper_scenario  # noqa: E402
from edgepos.sim.sensors import environment, rsu_imu_epochs  # noqa: E402


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(values, q))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=3000)
    args = parser.parse_args()

    scenario = rsu_imu_paper_scenario()
    epochs = rsu_imu_epochs(scenario, np.random.default_rng(7))
    env = environment(scenario)
    pipeline = get_pipeline("rsu_imu")
    options = pipeline.resolve_options({})
    x0 = scenario.initial_state
    state = pipeline.create(options, InitialState(x0[0], x0[3], x0[1], x0[4]))
    warmup = 200  # a realistic, converged state to time from
    _, state = pipeline.process(state, [o for epoch in epochs[:warmup] for o in epoch], env)
    session = _decode(state)
    bank = _bank(_options_key(options))
    epoch = epochs[warmup]
    rsu_obs = [o for o in epoch if o.kind == "rsu"]
    gyro = [o for o in epoch if o.kind == "gyro"][0]
    positions = np.array([[env.rsu(o.rsu_id).x, env.rsu(o.rsu_id).y] for o in rsu_obs])
    measurement = Stacked(
        [RsuRangeBearing(positions, options["range_std"], options["bearing_std"]), GyroYawRate(options["gyro_std"])]
    )
    observed = np.concatenate([np.ravel([[o.range, o.bearing] for o in rsu_obs]), [gyro.yaw_rate]])
    correction = JointCorrection(measurement, observed)
    dt = scenario.period
    sub_means = [session.means[j, list(m.components)] for j, m in enumerate(bank.models)]
    sub_covs = [session.covs[j][np.ix_(m.components, m.components)] for j, m in enumerate(bank.models)]

    def project_step():
        prediction = bank.predict(session.means, session.covs, session.probabilities, dt)
        return bank.correct(prediction, correction)

    def baseline_step():
        return baseline_2imm_ckf.step(
            bank.models, bank.transition, bank.priority, sub_means, sub_covs, session.probabilities,
            dt, measurement, observed,
        )

    pipeline_epoch = list(epoch)

    def pipeline_step():
        return pipeline.process(state, pipeline_epoch, env)

    timings: dict[str, list[float]] = {"project bank step": [], "rsu_imu pipeline epoch": [], "numpy baseline": []}
    functions = {"project bank step": project_step, "rsu_imu pipeline epoch": pipeline_step, "numpy baseline": baseline_step}
    for function in functions.values():
        function()
    for _ in range(args.iterations):
        for name, function in functions.items():
            start = time.perf_counter()
            function()
            timings[name].append((time.perf_counter() - start) * 1e6)

    result = project_step()
    _, _, base_probabilities, base_mean, base_cov = baseline_step()
    agreement = max(
        float(np.max(np.abs(result.output.mean - base_mean))),
        float(np.max(np.abs(result.output.cov - base_cov))),
        float(np.max(np.abs(result.probabilities - base_probabilities))),
    )

    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, python {platform.python_version()}, numpy {np.__version__}")
    print(f"2IMM-CKF step, models CA/AT/Singer, {len(rsu_obs)} RSUs + gyro, {args.iterations} interleaved iterations")
    print(f"{'what':28s} {'median us':>10s} {'p90 us':>10s}")
    for name, values in timings.items():
        print(f"{name:28s} {statistics.median(values):10.1f} {percentile(values, 90):10.1f}")
    speedup = statistics.median(timings["numpy baseline"]) / statistics.median(timings["project bank step"])
    print(f"baseline / project (median): {speedup:.2f}x")
    print(f"max |project - baseline| over fused mean, covariance, probabilities: {agreement:.2e}")
    return 0 if agreement < 1e-8 else 1


if __name__ == "__main__":
    sys.exit(main())
