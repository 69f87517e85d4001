"""The former home of five timing benchmarks, now one script each; this forwards to them.

    python benchmarks/timing.py step ...       -> python benchmarks/step_time.py ...
    python benchmarks/timing.py profile ...    -> python benchmarks/profile_step.py ...
    python benchmarks/timing.py typecheck ...  -> python benchmarks/typecheck_overhead.py ...
    python benchmarks/timing.py memory ...     -> python benchmarks/memory.py ...
    python benchmarks/timing.py quickstart ... -> python benchmarks/quickstart.py ...

The subcommand is replaced by its script, which runs with the same arguments, in this process
(so a result file records the script's own command). Commands printed in the documents and
recorded in older result files keep working this way.
"""

import os
import sys
from pathlib import Path

SCRIPTS = {
    "step": "step_time.py",
    "profile": "profile_step.py",
    "typecheck": "typecheck_overhead.py",
    "memory": "memory.py",
    "quickstart": "quickstart.py",
}


def main() -> None:
    command = sys.argv[1] if len(sys.argv) > 1 else None
    if command in ("-h", "--help"):
        print(__doc__.strip())
        return
    if command not in SCRIPTS:
        why = "a subcommand is needed" if command is None else f"unknown subcommand {command!r}"
        print(f"{__doc__.strip()}\n\ntiming.py: {why} (known: {', '.join(SCRIPTS)})", file=sys.stderr)
        sys.exit(2)
    script = Path(__file__).resolve().with_name(SCRIPTS[command])
    print(f"timing.py {command} is now benchmarks/{script.name}; running it", file=sys.stderr, flush=True)
    sys.stdout.flush()
    # The interpreter's own options (`python -X ...`), then the script and the arguments.
    options = sys.orig_argv[1 : len(sys.orig_argv) - len(sys.argv)]
    os.execv(sys.executable, [sys.executable, *options, str(script), *sys.argv[2:]])


if __name__ == "__main__":
    main()
