"""Count how often a command reads each point cloud (issue 16: each scan read once per run).

    python benchmarks/count_reads.py READS.log -- plotmosaic register-plot M.toml --out OUT

Runs the command with a `sitecustomize` (in a temporary folder put first on PYTHONPATH) that wraps
`plotmosaic.io.las.read_cloud` (whole-cloud reads) and `iter_chunks` (streamed reads) in every
Python process of the run, worker processes included, and appends one line per call to READS.log;
then prints the calls per file. Nothing in plotmosaic itself is changed or needed for this.
"""

from __future__ import annotations

import collections
import os
import subprocess
import sys
import tempfile
from pathlib import Path

HOOK = """
import functools, json, os, time
def _install():
    import plotmosaic.io.las as las
    log = os.environ["PLOTMOSAIC_COUNT_READS"]
    def wrap(name):
        inner = getattr(las, name)
        @functools.wraps(inner)  # same name and module: pickles by reference like the original
        def counted(path, *args, **kwargs):
            with open(log, "a") as f:
                f.write(json.dumps({"call": name, "path": str(path), "pid": os.getpid(),
                                    "t": time.time()}) + "\\n")
            return inner(path, *args, **kwargs)
        setattr(las, name, counted)
    for name in ("read_cloud", "iter_chunks"):
        wrap(name)
try:
    _install()
except Exception as exc:  # the count must never change what the command does
    import sys
    print(f"count_reads: not installed ({exc})", file=sys.stderr)
"""


def main(argv: list[str]) -> int:
    if "--" not in argv or argv.index("--") != 1:
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 2
    log = Path(argv[0]).resolve()
    command = argv[2:]
    log.write_text("")
    with tempfile.TemporaryDirectory() as hook_dir:
        (Path(hook_dir) / "sitecustomize.py").write_text(HOOK)
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [hook_dir, env.get("PYTHONPATH")]))
        env["PLOTMOSAIC_COUNT_READS"] = str(log)
        rc = subprocess.call(command, env=env)
    import json

    calls = collections.Counter()
    for line in log.read_text().splitlines():
        rec = json.loads(line)
        calls[(rec["call"], rec["path"])] += 1
    for (call, path), n in sorted(calls.items(), key=lambda e: e[0][1]):
        print(f"{n:4d}  {call:12s} {path}")
    print(f"exit {rc}; {sum(calls.values())} reads of {len({p for _, p in calls})} files")
    return rc


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
