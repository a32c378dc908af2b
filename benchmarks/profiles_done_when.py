"""The motor-profiles issue's done-when, run as a user runs it, its figures written to JSON::

    python benchmarks/profiles_done_when.py --out benchmarks/results/profiles_done_when.json

Runs ``fiberplan plan --instrument moons -n 61 --scenario-kind unfold --seed 1 --planner mpc
--out m.h5 --json && fiberplan profiles m.h5 --out p.h5 --json && fiberplan verify p.h5 --json``
in a temporary directory and keeps, of each command's JSON, what the issue asks about: reached,
collisions, motor-limit violations (in the plan's samples and in the profiles), segments per
joint, makespan before and after, verified.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine_info

COMMANDS = (
    "fiberplan plan --instrument moons -n 61 --scenario-kind unfold --seed 1 --planner mpc --out m.h5 --json",
    "fiberplan profiles m.h5 --out p.h5 --json",
    "fiberplan verify p.h5 --json",
)


def run(command: str, where: Path) -> dict:
    """One command's JSON output; a failing command stops the run with its message."""
    done = subprocess.run(command.split(), cwd=where, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        sys.exit(f"`{command}` exited with {done.returncode}:\n{done.stderr}")
    return json.loads(done.stdout)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        plan, profiles, verified = (run(c, Path(tmp)) for c in COMMANDS)
    keep_profiles = ("segments_median", "segments_p95", "segments_max", "limits", "verified_ok", "collisions", "motor_violations",
                     "makespan_before_s", "makespan_after_s", "discretise_s", "relaxed_segments", "refit_rounds", "followed_samples")
    result = {
        "name": "profiles-done-when",
        "date_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "machine": machine_info(),
        "command": " && ".join(COMMANDS),
        "plan": {k: plan.get(k) for k in ("reached", "targets", "collisions", "motor_violations", "makespan_s", "plan_wall_s")},
        "profiles": {k: profiles.get(k) for k in keep_profiles},
        "verify": {k: verified.get(k) for k in ("verified_ok", "collisions", "motor_violations", "reached", "targets", "file_mismatches")},
    }
    args.out.write_text(json.dumps(result, indent=1))
    print(json.dumps({part: result[part] for part in ("plan", "profiles", "verify")}, indent=1))


if __name__ == "__main__":
    main()
