"""Benchmark: opening and copying logs of many chunks (the summary's chunk indexes).

An hour of 1024x1024 frames at 300 Hz is about 1.6 million chunks; each has a Chunk Index record
in the summary, which every process that opens the log reads. For logs of 10 thousand to 1
million chunks, written by the ``mcap`` library alone (two JSON channels, one message a chunk),
this prints, each figure measured in this run:

1. the CLI as a user runs it: wall seconds and peak RSS (GNU time ``%M``) of ``starlog info``
   (opens the log), of ``starlog filter --topic /camera/frame`` (opens it, reads every chunk,
   writes a log with a summary of its own) and of ``starlog verify`` (reads every record and
   compares each chunk index with its chunk);
2. beside it, the summary parse alone in this process: ``mcap``'s ``get_summary`` against
   starlog's ``read_file_summary`` (seconds, and the memory each keeps, from tracemalloc);
3. what a summary that does not repeat the schemas and channels costs (the same log written with
   ``repeat_schemas=False, repeat_channels=False``; starlog then reads them from the data section):
   ``starlog info`` and opening the file in this process (``McapFile``), with and without the copies.

Usage::

    python tools/bench_index.py                       # 10k, 100k and 1M chunks
    python tools/bench_index.py --quick               # 2k and 20k chunks
    python tools/bench_index.py --command "python other_starlog.py"   # time another starlog build

Run times on a 2-core machine: --quick about 5 s, the full run several minutes. No pass/fail
target: the figures are printed and the exit status is 0.
"""

from __future__ import annotations

import argparse
import gc
import os
import shlex
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from starlog.io.summary_section import read_file_summary
from starlog.io.mcap_file import McapFile

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_scale import _timed as timed  # noqa: E402  # wall seconds and peak RSS (MiB) of a command


def write_log(path: Path, chunks: int, *, repeat: bool = True) -> None:
    """``chunks`` messages on two channels, one a chunk (the ``mcap`` library's writer, no compression); with
    ``repeat=False``, a summary without the schema and channel records."""
    with open(path, "wb") as f:
        writer = Writer(f, chunk_size=1, compression=CompressionType.NONE, repeat_schemas=repeat,
                        repeat_channels=repeat)
        writer.start()
        schema = writer.register_schema(name="starlog.FrameInfo", encoding="jsonschema", data=b'{"type":"object"}')
        frame = writer.register_channel(topic="/camera/frame", message_encoding="json", schema_id=schema)
        other = writer.register_channel(topic="/other", message_encoding="json", schema_id=schema)
        for i in range(chunks):
            t = i * 3_333_333
            writer.add_message(frame if i % 2 else other, log_time=t, publish_time=t, data=b'{"frame":%d}' % i,
                               sequence=i)
        writer.finish()


def parse_alone(path: Path) -> list[tuple[str, float, float]]:
    """Seconds and MB kept of each summary parser, in this process."""
    rows = []
    for name, parse in (("mcap get_summary", lambda f: make_reader(f).get_summary()),
                        ("starlog read_file_summary", read_file_summary)):
        gc.collect()
        with open(path, "rb") as f:
            start = time.perf_counter()
            parse(f)
            seconds = time.perf_counter() - start
            f.seek(0)
            tracemalloc.start()
            summary = parse(f)
            kept, _ = tracemalloc.get_traced_memory()
            tracemalloc.stop()
            del summary
        rows.append((name, seconds, kept / 1e6))
    return rows


def open_seconds(path: Path, repeat: int = 5) -> float:
    """The best of ``repeat`` opens of ``path`` (summary read and checked, definitions found), in this process."""
    best = float("inf")
    for _ in range(repeat):
        start = time.perf_counter()
        McapFile(path).close()
        best = min(best, time.perf_counter() - start)
    return best


def unrepeated_rows(folder: Path, chunks: int, starlog: list[str]) -> tuple[float, ...]:
    """``info`` seconds and open seconds of the log of ``chunks`` chunks with the summary's copies, then without."""
    figures = []
    for repeat in (True, False):
        log = folder / f"repeat_{repeat}_{chunks}.mcap"
        write_log(log, chunks, repeat=repeat)
        figures += [timed([*starlog, "info", str(log)])[0], open_seconds(log)]
        log.unlink()
    return tuple(figures)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="2k and 20k chunks (about 5 s)")
    parser.add_argument("--command", default=f"{shlex.quote(sys.executable)} -m starlog",
                        help="how to run starlog [default: this interpreter's -m starlog]")
    args = parser.parse_args()
    sizes = [2_000, 20_000] if args.quick else [10_000, 100_000, 1_000_000]
    starlog = shlex.split(args.command)
    print(f"# starlog bench_index  (cores: {os.cpu_count()}; starlog run as: {args.command})\n")
    print("| chunks | file MB | `info` s | `info` peak MiB | `filter` s | `filter` peak MiB | `verify` s "
          "| `verify` peak MiB |")
    print("|---|---|---|---|---|---|---|---|")
    parses, unrepeated = [], []
    with tempfile.TemporaryDirectory(dir=os.environ.get("BENCH_TMP")) as tmp:
        for n in sizes:
            log = Path(tmp) / f"chunks_{n}.mcap"
            write_log(log, n)
            info = timed([*starlog, "info", str(log)])
            out = Path(tmp) / "filtered.mcap"
            filtered = timed([*starlog, "filter", str(log), "-o", str(out), "--topic", "/camera/frame", "--force",
                              "--quiet"])
            verified = timed([*starlog, "verify", str(log)])
            print(f"| {n:,} | {log.stat().st_size / 1e6:.0f} | {info[0]:.2f} | {info[1]:.0f} | {filtered[0]:.2f} "
                  f"| {filtered[1]:.0f} | {verified[0]:.2f} | {verified[1]:.0f} |", flush=True)
            parses += [(n, *row) for row in parse_alone(log)]
            log.unlink()
            unrepeated.append((n, *unrepeated_rows(Path(tmp), n, starlog)))
    print("\nThe summary parse alone, in this process:\n")
    print("| chunks | parser | seconds | MB kept |")
    print("|---|---|---|---|")
    for n, name, seconds, kept in parses:
        print(f"| {n:,} | {name} | {seconds:.2f} | {kept:.1f} |")
    print("\nA summary without the schema and channel records (read from the data section instead):\n")
    print("| chunks | `info` s, with copies | `info` s, without | open s, with copies | open s, without |")
    print("|---|---|---|---|---|")
    for n, info_with, open_with, info_without, open_without in unrepeated:
        print(f"| {n:,} | {info_with:.2f} | {info_without:.2f} | {open_with:.4f} | {open_without:.4f} |")


if __name__ == "__main__":
    main()
