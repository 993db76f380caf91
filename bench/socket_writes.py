"""Benchmark: what a response's second socket write costs the worker (uvloop, TCP on loopback).

uvicorn writes a response's head and its body in two ``transport.write`` calls; joined, they are one. This
writes a batch answer's head and a body of ``--body`` bytes both ways on one loopback TCP connection
(TCP_NODELAY, as uvicorn sets it) to a reader in another process, the two ways alternated in rounds of
``--writes`` responses, each response followed by one turn of the event loop, and prints the thread CPU per
response (minimum and median over the rounds) with the load average. Issue 19's "one socket write per
response" was measured with it and dropped (docs/benchmarks.md, "The worker's CPU outside the filter,
round two").

    python bench/socket_writes.py [--body 5200] [--writes 300] [--rounds 15]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import socket
import statistics
import subprocess
import sys
import time

import uvloop

READER = """
import socket, sys
connection = socket.create_connection(("127.0.0.1", int(sys.argv[1])))
while connection.recv(1 << 20):
    pass
"""

HEAD = (
    b"HTTP/1.1 200 OK\r\ncontent-length: %d\r\ncontent-type: application/json\r\n"
    b"x-request-id: 0123456789abcdef0123456789abcdef\r\n\r\n"
)


async def measure(connection: socket.socket, args: argparse.Namespace) -> dict[str, list[float]]:
    """Thread CPU (µs) per response of each way, one figure per round."""
    head, body = HEAD % args.body, b"x" * args.body
    transport, _ = await asyncio.get_running_loop().connect_accepted_socket(asyncio.Protocol, connection)
    per_response: dict[str, list[float]] = {"two writes": [], "one write": []}
    try:
        for round_ in range(args.rounds):
            ways = list(per_response) if round_ % 2 == 0 else list(reversed(per_response))
            for way in ways:
                started = time.thread_time_ns()
                for _ in range(args.writes):
                    if way == "two writes":
                        transport.write(head)
                        transport.write(body)
                    else:
                        transport.write(head + body)
                    await asyncio.sleep(0)
                per_response[way].append((time.thread_time_ns() - started) / args.writes / 1e3)
    finally:
        transport.close()
    return per_response


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--body", type=int, default=5200, help="body bytes (a 20-fix answer: about 5.2 kB)")
    parser.add_argument("--writes", type=int, default=300, help="responses per round and way")
    parser.add_argument("--rounds", type=int, default=15)
    args = parser.parse_args()
    before = os.getloadavg()[0]
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        reader = subprocess.Popen([sys.executable, "-c", READER, str(listener.getsockname()[1])])
        connection, _ = listener.accept()
    connection.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    try:
        results = uvloop.run(measure(connection, args))
    finally:
        reader.wait(timeout=30)
    print(
        f"head {len(HEAD % args.body)} B + body {args.body} B, {args.rounds} rounds x {args.writes} responses; "
        f"load average {before:.2f} before, {os.getloadavg()[0]:.2f} after"
    )
    for way, figures in results.items():
        print(
            f"  {way:10s}  {min(figures):6.2f} us min  {statistics.median(figures):6.2f} us median per response"
        )


if __name__ == "__main__":
    main()
