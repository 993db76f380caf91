"""Benchmark: what the batch route spends on a request body before the filter, per 20-epoch RSU batch.

Times, in one process and interleaved, FastAPI's two passes (the standard library's ``json.loads``, then
the model's validation of the dicts, as FastAPI validates a body) against the one pass the sessions routes
take (``model_validate_json`` on the bytes: ``api/one_pass_body.py``), and the replay digest's JSON of the
batch written through the measurement union against each measurement's own class (``serialize_as_any``,
the same bytes). Prints the minimum over repeats (the least disturbed by other work on the machine) in
microseconds, with the load average.

    python bench/request_parsing.py [--epochs 20] [--repeats 9]
"""

from __future__ import annotations

import argparse
import json
import os
import timeit

from edgepos.api.measurement_schemas import BatchIn
from pydantic import TypeAdapter


def batch_document(epochs: int) -> bytes:
    """A vehicle's batch as it goes on the wire: per epoch a gyro reading and four RSU range/bearing pairs,
    timestamps jittered by a millisecond or two."""
    measurements: list[dict[str, object]] = []
    for k in range(epochs):
        t = round(k * 0.05 + 0.0013 * ((k * 7) % 3), 6)
        measurements.append({"type": "gyro", "t": t, "yaw_rate": 0.0123})
        for r in range(4):
            measurements.append(
                {"type": "rsu", "t": t, "rsu_id": f"S+{50 * r:03d}", "range": 10.25 + r, "bearing": 0.3 * r}
            )
    return json.dumps({"seq": 5, "measurements": measurements}).encode()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--epochs", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--number", type=int, default=500, help="calls per repeat")
    args = parser.parse_args()
    body = batch_document(args.epochs)
    two_pass = TypeAdapter(BatchIn)
    batch = BatchIn.model_validate_json(body)
    assert two_pass.validate_python(json.loads(body), from_attributes=True) == batch
    assert batch.model_dump_json(serialize_as_any=True) == batch.model_dump_json()
    rows = {
        "two passes: json.loads + validation (FastAPI)": lambda: two_pass.validate_python(
            json.loads(body), from_attributes=True
        ),
        "one pass: model_validate_json": lambda: BatchIn.model_validate_json(body),
        "digest JSON through the union (model_dump_json)": lambda: batch.model_dump_json(),
        "digest JSON by each measurement's class (as any)": lambda: batch.model_dump_json(
            serialize_as_any=True
        ),
    }
    load = os.getloadavg()
    best = {name: float("inf") for name in rows}
    for _ in range(args.repeats):  # interleaved: a busy moment hits every row alike
        for name, call in rows.items():
            best[name] = min(best[name], timeit.timeit(call, number=args.number) / args.number)
    print(
        f"{len(body)} bytes, {len(batch.measurements)} measurements ({args.epochs} epochs); "
        f"min over {args.repeats} repeats of {args.number} calls; load average {load[0]:.2f} before, "
        f"{os.getloadavg()[0]:.2f} after"
    )
    for name, seconds in best.items():
        print(f"  {name:<52} {seconds * 1e6:8.1f} us")


if __name__ == "__main__":
    main()
