"""Run `skyeyes-bench` on a list of hostile cases in one process under a memory limit.

Usage: python _hostile_runner.py CASES.json REPORT.jsonl MEMORY_BYTES SECONDS

Each case is {"id", "argv"}. stdout and stderr are captured at the file-descriptor level (so a
C library's own lines, e.g. libpng's, are seen too); each case has SECONDS before SIGALRM stops
it. One JSON line per case is appended to REPORT as soon as it ends, so a case that kills the
process still leaves the earlier ones reported.
"""

import json
import os
import resource
import signal
import sys
import tempfile
import time
import traceback


class _Timeout(Exception):
    pass


def _alarm(signum, frame):
    raise _Timeout()


def main() -> None:
    cases_file, report_file, memory, seconds = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
    resource.setrlimit(resource.RLIMIT_AS, (memory, memory))
    signal.signal(signal.SIGALRM, _alarm)
    from skyeyes_bench.cli import main as cli_main

    cases = json.loads(open(cases_file).read())
    saved = os.dup(1), os.dup(2)
    for case in cases:
        with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(out.fileno(), 1)
            os.dup2(err.fileno(), 2)
            t0 = time.monotonic()
            rc, exc = None, None
            signal.alarm(seconds)
            try:
                rc = cli_main(case["argv"])
            except SystemExit as e:
                rc = e.code if isinstance(e.code, int) else 2
            except _Timeout:
                exc = f"timed out after {seconds} s"
            except BaseException:  # noqa: BLE001 - the traceback is the finding
                exc = traceback.format_exc()
            finally:
                signal.alarm(0)
                sys.stdout.flush()
                sys.stderr.flush()
                os.dup2(saved[0], 1)
                os.dup2(saved[1], 2)
            dt = time.monotonic() - t0
            out.seek(0)
            err.seek(0)
            rec = {"id": case["id"], "rc": rc, "exc": exc, "seconds": dt,
                   "stdout": out.read().decode("utf-8", "replace"), "stderr": err.read().decode("utf-8", "replace")}
        with open(report_file, "a") as f:
            f.write(json.dumps(rec) + "\n")


if __name__ == "__main__":
    main()
