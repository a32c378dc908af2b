"""The ``fiberplan`` command line: plan, verify, show, animate, scenario, instruments, planners.

Exit status: 0 success; 1 ``verify`` found a collision, limit violation, non-finite sample or
file inconsistency (or ``plan --strict`` did); 2 bad input (unknown preset, malformed file,
invalid scenario, bad setting, unsafe output path...), reported in one line without a
traceback and before any work starts; 3 a sweep lost every worker (finished runs are kept);
70 an internal error (a bug: one line; ``FIBERPLAN_DEBUG=1`` shows the traceback); 130
interrupted.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import click

from fiberplan._atomic import check_output_path
from fiberplan._json import json_ready as _json_ready
from fiberplan.errors import FiberplanError, InfrastructureError

DEFAULT_PLANNER = "mpc"
MAX_SEED = 2**63 - 1
EXIT_INFRASTRUCTURE = 3
EXIT_INTERNAL = 70

HDF5_SUFFIXES = (".h5", ".hdf5")
IMAGE_SUFFIXES = (".png", ".pdf", ".svg", ".jpg", ".jpeg", ".tif", ".tiff", ".webp", ".eps", ".ps")
ANIMATION_SUFFIXES = (".gif", ".mp4")
JSON_SUFFIXES = (".json",)
PARQUET_SUFFIXES = (".parquet",)

SEED = click.IntRange(0, MAX_SEED)


class _FilePath(click.Path):
    """A path option or argument: refused in one line when no file system could hold it."""

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        if isinstance(value, str) and ("\x00" in value or value == ""):
            self.fail(f"{value!r} is not a usable path", param, ctx)
        return super().convert(value, param, ctx)


PATH = _FilePath(path_type=Path)
POSITIONERS = click.IntRange(1, 50_000)


def _explicit(ctx: click.Context, *names: str) -> list[str]:
    """Options the user gave on the command line (not defaults), as ``--option`` names."""
    from click.core import ParameterSource

    return [f"--{n.replace('_', '-')}" for n in names if ctx.get_parameter_source(n) == ParameterSource.COMMANDLINE]


def _instrument_arg(text: str) -> tuple[Any, str | None, str]:
    """An ``--instrument`` value: the instrument, its preset name (or None) and what was used."""
    from fiberplan.instrument_io import instrument_source, load_instrument

    kind, where = instrument_source(text)
    inst = load_instrument(text)
    return inst, (where if kind == "preset" else None), (f"preset {where}" if kind == "preset" else f"file {where}")


def _print_not_reached(summary: dict[str, Any], limit: int = 20) -> None:
    why = summary.get("not_reached") or {}
    for pid, reason in list(why.items())[:limit]:
        click.echo(f"  positioner {pid}: {reason}")
    if len(why) > limit:
        click.echo(f"  ... and {len(why) - limit} more not reached (use --json for all)")


def _limit_text(v: Any, convention: str) -> str:
    """A limit violation in degrees (beta in the scenario file's convention), worst excess first."""
    import math

    from fiberplan.scenario import _deg

    first = f", first at t = {v.t_first_s:.3f} s" if math.isfinite(v.t_first_s) else ""
    if v.kind == "speed":
        return (f"speed violation: positioner {v.positioner_id} {v.joint} at {_deg(math.degrees(abs(v.value)))} deg/s, limit "
                f"{_deg(math.degrees(v.limit))} deg/s (worst at t = {v.t_s:.3f} s{first})")
    shift = 180.0 if convention == "folded" and v.joint == "beta" else 0.0
    value, limit = math.degrees(v.value) - shift, math.degrees(v.limit) - shift
    return (f"hard-stop violation: positioner {v.positioner_id} {v.joint} at {_deg(value)} deg, {_deg(abs(value - limit))} deg beyond "
            f"its stop at {_deg(limit)} deg{' (beta from the folded arm)' if shift else ''} (worst at t = {v.t_s:.3f} s{first})")


def _motor_text(v: Any) -> str:
    """A motor-limit violation: positioner, joint, kind, the worst value and when."""
    import math

    from fiberplan.scenario import _deg

    when = f"worst at t = {v.t_s:.3f} s, first at t = {v.t_first_s:.3f} s"
    if v.kind == "min_speed":
        what = f"turns at {_deg(math.degrees(v.value))} deg/s, below its minimum {_deg(math.degrees(v.limit))} deg/s"
    elif v.kind == "speed_change":
        what = f"changes speed by {v.value:.0%} between two commands (limit {v.limit:.0%})"
    elif v.kind == "reversal":
        what = f"reverses without stopping (a speed jump of {_deg(math.degrees(v.value))} deg/s)"
    elif v.kind == "acceleration":
        what = (f"accelerates at {_deg(math.degrees(v.value))} deg/s^2 as executed with the ramps, above "
                f"{_deg(math.degrees(v.limit))} deg/s^2 (reversing with less than a ramp time of stop)")
    elif v.kind == "start_stops":
        what = f"starts from rest {int(v.value)} times (limit {int(v.limit)})"
    else:
        what = f"has {int(v.value)} constant-speed segments (limit {int(v.limit)})"
    return f"positioner {v.positioner_id} {v.joint} {what} ({when})"


def _warn(messages: Sequence[str]) -> None:
    for message in messages:
        click.echo(f"warning: {message}", err=True)


def _print_table(summary: dict[str, Any], keys: Sequence[str]) -> None:
    width = max(len(k) for k in keys)
    for key in keys:
        value = summary.get(key)
        if isinstance(value, float):
            text = "n/a" if not math.isfinite(value) else f"{value:.4g}"
        else:
            text = "n/a" if value is None else str(value)
        click.echo(f"  {key:<{width}}  {text}")


def _parse_settings(pairs: Sequence[str]) -> dict[str, Any]:
    settings: dict[str, Any] = {}
    for item in pairs:
        if "=" not in item:
            raise click.BadParameter(f"expected KEY=VALUE, found {item!r}", param_hint="--set")
        key, raw = item.split("=", 1)
        try:
            settings[key.strip()] = json.loads(raw)
        except json.JSONDecodeError:
            settings[key.strip()] = raw
    return settings


_SUMMARY_KEYS = (
    "planner", "instrument", "scenario_kind", "n_positioners", "seed", "targets", "reached", "success_rate", "held",
    "deadlocked", "unfinished", "failed", "displaced", "infeasible", "locked", "collisions", "limit_violations", "motor_violations",
    "makespan_s", "lower_bound_s",
    "makespan_over_bound", "plan_wall_s", "route",
)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="fiberplan")
def cli() -> None:
    """Plan collision-free motions for theta-phi fiber positioners, verify and look at them."""


def _build_scenario(
    ctx: click.Context, scenario_file: Path | None, instrument: str, positioners: int, radius_mm: float | None, kind: str, seed: int,
    min_start_clearance_mm: float | None = None,
) -> tuple[Any, str]:
    """The scenario to plan and a line saying where its instrument came from.

    With ``--scenario``, the generator options cannot apply and are refused when given;
    ``--instrument`` then replaces the file's instrument (said in the output).
    """
    if scenario_file is not None:
        from fiberplan.scenario import load_scenario

        ignored = _explicit(ctx, "positioners", "radius_mm", "scenario_kind", "seed", "min_start_clearance_mm")
        if ignored:
            raise click.UsageError(f"{', '.join(ignored)} cannot be used with --scenario (the file gives the positioners and targets)")
        sc = load_scenario(scenario_file)
        if _explicit(ctx, "instrument"):
            inst, preset, used = _instrument_arg(instrument)
            return sc.with_instrument(inst, preset), f"{used} (replaces the scenario file's {sc.instrument.name!r})"
        return sc, f"from the scenario file ({'preset ' + sc.instrument_preset if sc.instrument_preset else 'embedded table'})"
    from fiberplan.generate import make_scenario
    from fiberplan.studies.scenarios import HARD_KIND, hard_scenario

    inst, preset, used = _instrument_arg(instrument)
    if kind == HARD_KIND:
        if radius_mm is not None:
            raise click.UsageError("--radius-mm does not apply to --scenario-kind hard (a hexagonal group of -n positioners)")
        if min_start_clearance_mm is not None:
            raise click.UsageError("--min-start-clearance-mm does not apply to --scenario-kind hard (its starts are drawn close on purpose)")
        return hard_scenario(instrument, positioners, seed), used
    return make_scenario(inst, positioners, kind, seed, radius_mm=radius_mm, instrument_preset=preset,
                         min_start_clearance_mm=min_start_clearance_mm), used


@cli.command()
@click.option("--instrument", default="desi", show_default=True, help="Preset name (desi, moons, sdss) or instrument .toml file.")
@click.option("--positioners", "-n", default=500, show_default=True, type=POSITIONERS, help="Positioners in the hexagonal patch.")
@click.option("--radius-mm", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Lay out a full focal plane of this radius instead of a patch.")
@click.option("--scenario-kind", default="random", show_default=True, help="random, unfold, fold, clustered or hard.")
@click.option("--seed", default=0, show_default=True, type=SEED, help="Seed of the scenario generator.")
@click.option("--min-start-clearance-mm", "min_start_clearance_mm", type=click.FloatRange(min=0), default=None,
              help="Smallest clearance between neighbours in a drawn start (default: the instrument's safety margin; 0: none).")
@click.option("--scenario", "scenario_file", type=PATH, default=None, help="Plan this scenario file instead.")
@click.option("--planner", default=DEFAULT_PLANNER, show_default=True, help="Planner name (see `fiberplan planners`).")
@click.option("--set", "settings", multiple=True, metavar="KEY=VALUE", help="Planner setting override (repeatable).")
@click.option("--out", type=PATH, default=None, help="Write the trajectory to this HDF5 file (.h5).")
@click.option("--picture", type=PATH, default=None, help="Write a snapshot (first collision, else the end).")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of the table.")
@click.option("--no-verify", is_flag=True, help="Skip the independent verifier.")
@click.option("--strict", is_flag=True, help="Exit with status 1 if the verifier finds a collision or violation.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
@click.pass_context
def plan(
    ctx: click.Context, instrument: str, positioners: int, radius_mm: float | None, scenario_kind: str, seed: int,
    min_start_clearance_mm: float | None, scenario_file: Path | None, planner: str, settings: tuple[str, ...], out: Path | None,
    picture: Path | None, as_json: bool, no_verify: bool, strict: bool, quiet: bool,
) -> None:
    """Plan a generated or given scenario, verify it, and print a summary."""
    # Everything that can be refused is refused before any planning.
    if out is not None:
        check_output_path(out, what="--out", suffixes=HDF5_SUFFIXES, inputs=[scenario_file])
    if picture is not None:
        check_output_path(picture, what="--picture", suffixes=IMAGE_SUFFIXES, inputs=[scenario_file, out])
        if out is not None and os.path.abspath(out) == os.path.abspath(picture):
            raise click.UsageError("--out and --picture name the same file")
    if scenario_file is not None and not scenario_file.is_file():
        from fiberplan.errors import ScenarioError

        raise ScenarioError(f"scenario file {str(scenario_file)!r} {'is not a regular file' if scenario_file.exists() else 'does not exist'}")
    from tqdm import tqdm

    from fiberplan.metrics import summarize
    from fiberplan.planners import make_settings
    from fiberplan.planners import plan as run_planner
    from fiberplan.trajectory import save_result
    from fiberplan.verify import verify as run_verify

    overrides = _parse_settings(settings)
    from fiberplan.planners import settings_class

    settings_class(planner)  # an unknown planner is refused before the scenario is built
    scenario, instrument_used = _build_scenario(ctx, scenario_file, instrument, positioners, radius_mm, scenario_kind, seed,
                                                min_start_clearance_mm)
    planner_settings = make_settings(planner, scenario, overrides)
    # The planners report the share of their step budget used (an upper bound on the work left)
    # and their phase; the bar shows both and the time spent, not a remaining-time guess.
    bar = tqdm(total=100, desc=f"{planner} x {scenario.n_positioners}: planning", disable=True if quiet else None, file=sys.stderr,
               leave=False, bar_format="{desc} {percentage:3.0f}% |{bar}| {elapsed}")

    def progress(fraction: float, phase: str | None = None) -> None:
        if phase is not None:
            bar.set_description_str(f"{planner} x {scenario.n_positioners}: {phase}", refresh=False)
        bar.update(max(0, int(100 * min(fraction, 1.0)) - bar.n))

    started = time.perf_counter()
    try:
        result = run_planner(scenario, planner, planner_settings, progress=progress)
    finally:
        bar.close()
    split = {"plan": time.perf_counter() - started}
    live = not quiet and sys.stderr.isatty()
    if not no_verify and live:
        click.echo(f"{planner} x {scenario.n_positioners}: verifying...", err=True, nl=False)
    started = time.perf_counter()
    report = None if no_verify else run_verify(scenario, result.trajectory)
    if not no_verify:
        split["verify"] = time.perf_counter() - started
        if live:
            click.echo("\r" + " " * 60 + "\r", err=True, nl=False)
    summary = summarize(result, report)
    summary["instrument_source"] = instrument_used
    if report is None:
        summary["collisions"] = None
    if out is not None:
        started = time.perf_counter()
        save_result(result, out)
        split["write"] = time.perf_counter() - started
        summary["out"] = str(out)
    summary["time_split_s"] = {phase: round(seconds, 3) for phase, seconds in split.items()}
    if picture is not None:
        from fiberplan.plotting import default_snapshot_time, save_snapshot

        times = [c.t_first_s for c in report.collisions] if report is not None else []
        save_snapshot(result, picture, default_snapshot_time(result, times))
        summary["picture"] = str(picture)
    summary["warnings"] = list(result.warnings)
    stretched = (result.stats or {}).get("stretch")
    if stretched is not None:  # --set stretch=true: what it did
        summary["stretch"] = stretched
    if as_json:
        click.echo(json.dumps(_json_ready(summary)))
    else:
        click.echo(f"fiberplan plan: {scenario.name or scenario.kind}")
        keys = (*_SUMMARY_KEYS, "instrument_source", *(k for k in ("out", "picture") if k in summary))
        extra = {"time_split_s": ", ".join(f"{phase} {seconds:.2f} s" for phase, seconds in summary["time_split_s"].items())}
        if stretched is not None:
            before, after = stretched["energy_before_rad2_s"], stretched["energy_after_rad2_s"]
            change = f" ({after / before - 1:+.1%})" if before > 0 else ""
            extra["stretch"] = f"{stretched['positioners']} positioner(s) stretched, energy {before:.4g} -> {after:.4g} rad^2/s{change}"
            keys = (*keys, "stretch")
        _print_table(summary | extra, (*keys, "time_split_s"))
        _print_not_reached(summary)
    if scenario.infeasible:
        _warn([f"{len(scenario.infeasible)} target(s) cannot be reached at all and were not planned (they hold): "
               + "; ".join(f"positioner {scenario.ids[k]}: {why}" for k, why in list(scenario.infeasible.items())[:5])])
    _warn(result.warnings)
    if report is not None and not report.ok:
        click.echo(
            f"warning: the verifier found {report.n_collisions} colliding pair(s) and "
            f"{len(report.limit_violations)} limit violation(s); run `fiberplan verify` on the file for details",
            err=True,
        )
        if strict:
            sys.exit(1)


@cli.command()
@click.argument("file", type=PATH, required=False)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
@click.option("--max-events", default=20, show_default=True, type=click.IntRange(min=0), help="Events of each kind to list in the table.")
@click.option("--instrument", default=None, help="Check against this preset or instrument .toml file instead of the file's geometry.")
@click.option("--motors", is_flag=True, help="Exit with status 1 also when the instrument's motor limits are violated.")
@click.option("--paths", "paths_file", type=PATH, default=None,
              help="Check these exported profiles or time-stamped paths (.json, .csv; any planner's) instead of a trajectory file.")
@click.option("--scenario", "scenario_file", type=PATH, default=None, help="With --paths: the scenario the paths move (needed for CSV).")
def verify(file: Path | None, as_json: bool, max_events: int, instrument: str | None, motors: bool, paths_file: Path | None,
           scenario_file: Path | None) -> None:
    """Check a trajectory file: finite samples, hard stops, speeds, collisions at and between samples,
    and the file against itself; and the instrument's motor limits when it states them (listed
    apart: a planner's samples are not motor commands). A trajectory file holding motor
    profiles (``fiberplan profiles``) is also checked to rebuild from them exactly.

    With --paths (and --scenario), checks paths given as motor profiles (JSON, CSV) or
    time-stamped angle points (JSON) from any planner, rebuilt into a trajectory.

    Exits with status 1 when anything is violated (motor limits: with --motors).
    """
    if (file is None) == (paths_file is None):
        raise click.UsageError("give a trajectory FILE, or --paths P (with --scenario S.json when P holds no scenario)")
    if scenario_file is not None and paths_file is None:
        raise click.UsageError("--scenario goes with --paths (a trajectory file holds its scenario)")
    from fiberplan.metrics import summarize
    from fiberplan.ramps import verify_commands
    from fiberplan.trajectory import read_run
    from fiberplan.verify import check_run_file
    from fiberplan.verify import verify as run_verify

    geometry = _instrument_arg(instrument) if instrument is not None else None
    if paths_file is not None:  # motor commands: also as the motors execute them, where the instrument states a ramp time
        file = paths_file
        run = _paths_run(paths_file, scenario_file)
        report = verify_commands(run.scenario, run.trajectory, instrument=None if geometry is None else geometry[0])
    elif file is not None:
        from fiberplan.profile_io import holds_profiles, rebuilt_matches

        run = read_run(file)
        check = verify_commands if holds_profiles(file) else run_verify
        report = check(run.scenario, run.trajectory, instrument=None if geometry is None else geometry[0])
        mismatches, warnings = check_run_file(run)
        report.file_mismatches.extend(mismatches)
        differs = rebuilt_matches(run)
        if differs is not None:
            report.file_mismatches.append(differs)
        if geometry is None:
            report.warnings.extend(warnings)
    summary = summarize(run, report)
    summary["geometry"] = geometry[2] if geometry is not None else "the file's"
    if as_json:
        payload = summary | {"report": report.to_dict()}
        click.echo(json.dumps(_json_ready(payload)))
    else:
        click.echo(f"fiberplan verify: {file}")
        _print_table(summary, (*_SUMMARY_KEYS, "geometry", "verified_ok", "min_clearance_mm"))
        _print_not_reached(summary)
        for run_nf in report.non_finite[:max_events]:
            click.echo(
                f"  non-finite joint angles: positioner {run_nf.positioner_id} from t = {run_nf.t_first_s:.3f} s to "
                f"t = {run_nf.t_last_s:.3f} s ({run_nf.n_samples} sample(s))"
            )
        if len(report.non_finite) > max_events:
            click.echo(f"  ... and {len(report.non_finite) - max_events} more runs of non-finite samples (use --json for all)")
        for event in report.collisions[:max_events]:
            click.echo(
                f"  collision: positioners {event.id_i} ({event.capsule_i}) and {event.id_j} ({event.capsule_j}) "
                f"from t = {event.t_first_s:.3f} s, worst at t = {event.t_worst_s:.3f} s: distance "
                f"{event.min_distance_mm:.3f} mm < {event.required_mm:.3f} mm"
            )
        if report.n_collisions > max_events:
            click.echo(f"  ... and {report.n_collisions - max_events} more colliding pairs (use --json for all)")
        for v in report.limit_violations[:max_events]:
            click.echo(f"  {_limit_text(v, run.scenario.angle_convention)}")
        if report.motors_checked:
            click.echo(f"  motor limits: {len(report.motor_violations)} violation(s) (positioner, joint and kind; "
                       f"{'they fail the check' if motors else 'reported only; --motors makes them fail the check'})")
            for v in report.motor_violations[:max_events]:
                click.echo(f"    {_motor_text(v)}")
            if len(report.motor_violations) > max_events:
                click.echo(f"    ... and {len(report.motor_violations) - max_events} more (use --json for all)")
        else:
            click.echo("  motor limits: the instrument states none (unconstrained)")
        ramp_s = (run.scenario.instrument if geometry is None else geometry[0]).motors.ramp_time_s
        if report.executed_ramp_s is not None:
            click.echo(f"  checked as the motors execute these commands too, each speed change ramped over {report.executed_ramp_s:g} s "
                       f"(collisions and acceleration; the motion ends {report.executed_ramp_s:g} s after the commands)")
        elif ramp_s is not None:
            click.echo(f"  the instrument ramps speed changes over {ramp_s:g} s: a planner's samples are not checked against it; "
                       "motor commands are (fiberplan profiles, then verify the exported file)")
        if report.start_mismatch_ids:
            click.echo(f"  trajectory does not start at the scenario start for positioners {report.start_mismatch_ids[:10]}")
        for mismatch in report.file_mismatches:
            click.echo(f"  file inconsistency: {mismatch}")
    _warn(report.warnings)
    if not report.ok or (motors and not report.motors_ok):
        sys.exit(1)


def _scenario_on_layout(
    ctx: click.Context, instrument: str, kind: str, seed: int, layout_file: Path, targets_file: Path | None, out: Path,
    min_start_clearance_mm: float | None = None,
) -> None:
    """``fiberplan scenario --layout``: targets from a table (everyone starts at the datum), or drawn (--kind, --seed)."""
    from fiberplan.generate import make_scenario
    from fiberplan.layout_io import scenario_dict_from_tables
    from fiberplan.scenario import scenario_from_dict

    ignored = _explicit(ctx, "positioners", "radius_mm")
    if ignored:
        raise click.UsageError(f"{', '.join(ignored)} cannot be used with --layout (the layout gives the positioners)")
    inst, preset, used = _instrument_arg(instrument)
    if targets_file is not None:
        drawn = _explicit(ctx, "kind", "seed", "min_start_clearance_mm")
        if drawn:
            raise click.UsageError(f"{', '.join(drawn)} cannot be used with --targets (the targets come from the table)")
        sc = scenario_from_dict(scenario_dict_from_tables((inst, preset), layout_file, targets_file), origin=f"layout {str(layout_file)!r}")
    else:
        sc = make_scenario(inst, None, kind, seed, layout=layout_file, instrument_preset=preset, min_start_clearance_mm=min_start_clearance_mm)
    if sc.infeasible:
        _warn([f"{len(sc.infeasible)} target(s) cannot be reached at all (they will hold): "
               + "; ".join(f"positioner {sc.ids[k]}: {why}" for k, why in list(sc.infeasible.items())[:10])])
    sc.save(out)
    click.echo(f"wrote {out} ({sc.n_positioners} positioners from {layout_file}, {int(sc.wants_target.sum())} targets, "
               f"{int(sc.locked.sum())} locked, {'targets from ' + str(targets_file) if targets_file else f'{sc.kind}, seed {sc.seed}'}, "
               f"instrument {used})")


def _show_profiles(result: Any, file: Path, out: Path, profile_ids: str, t: float | None) -> None:
    """``fiberplan show --profiles``: discretise ``result`` and draw the chosen positioners."""
    from fiberplan.plotting import plot_motor_profiles, save_figure
    from fiberplan.profiles import discretise

    if t is not None:
        raise click.UsageError("--time draws a snapshot; --profiles draws whole profiles (give one of them)")
    try:
        ids = [int(text) for text in profile_ids.split(",") if text.strip()]
    except ValueError as e:
        raise click.BadParameter(f"expected positioner ids separated by commas (e.g. 3,17), found {profile_ids!r}", param_hint="--profiles") from e
    unknown = sorted(set(ids) - set(result.scenario.ids.tolist()))
    if not ids or unknown:
        raise click.BadParameter(f"positioner(s) {unknown or profile_ids!r} not in {file} (ids {int(result.scenario.ids.min())}.."
                                 f"{int(result.scenario.ids.max())})", param_hint="--profiles")
    made = discretise(result)
    save_figure(plot_motor_profiles(result, made, ids), out)
    click.echo(f"wrote {out} (positioners {', '.join(map(str, ids))}; profiles verified: {made.report is not None and made.report.ok})")


def _paths_run(paths_file: Path, scenario_file: Path | None) -> Any:
    """A plan result from exported profiles or foreign time-stamped paths (outcomes from where they end)."""
    import numpy as np

    from fiberplan.outcomes import outcome_labels
    from fiberplan.profile_io import read_paths
    from fiberplan.scenario import load_scenario
    from fiberplan.trajectory import PlanResult

    given = None if scenario_file is None else load_scenario(scenario_file)
    scenario, trajectory, form = read_paths(paths_file, given)
    outcome = outcome_labels(scenario, trajectory.joints[-1], np.zeros(scenario.n_positioners, dtype=bool))
    return PlanResult(scenario=scenario, trajectory=trajectory, outcome=outcome, planner=f"paths ({form})", settings={}, stats={}, plan_wall_s=0.0)


@cli.command()
@click.argument("run_file", metavar="RUN", type=PATH)
@click.option("--out", type=PATH, required=True, help="Where to write: .h5 (trajectory + /profiles), .json (segments) or .csv (one row per segment).")
@click.option("--format", "form", type=click.Choice(["h5", "json", "csv", "points"]), default=None,
              help="Export form (default: from the extension); points = time-stamped angle points (JSON).")
@click.option("--fraction", type=click.FloatRange(0.0, 1.0, min_open=True, max_open=True), default=0.5, show_default=True,
              help="Share of each pair's planned clearance the profiles may use (where the pauses leave motor-limit "
                   "violations, wider shares, 0.7 and 0.9, are tried too and the profiles with the fewest kept).")
@click.option("--pauses/--no-pauses", default=True, show_default=True,
              help="Mend what the fit leaves of the motor limits: creeps below the minimum speed move at the minimum and wait; "
                   "where a joint would reverse without a stop or jump in speed, everyone holds still for one sample step "
                   "(the makespan grows by the pauses; joints moving through a pause run through it where they can); where "
                   "that leaves violations or adds over 5 % of makespan, a fit from the planned samples with their zigzags "
                   "smoothed (verified) is tried too.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON summary.")
def profiles(run_file: Path, out: Path, form: str | None, fraction: float, pauses: bool, as_json: bool) -> None:
    """Turn a verified trajectory file into motor profiles: per positioner and joint, a few
    constant-speed segments within the instrument's motor limits, rebuilt and verified before
    anything is written.

    Exits with status 2 (nothing written) when the trajectory is not verified or the profiles
    cannot be; motor-limit violations left are reported (the profiles are still collision-free).
    """
    from fiberplan.profile_io import format_of, write_profiles
    from fiberplan.profiles import discretise
    from fiberplan.trajectory import load_result

    chosen = format_of(out, form)
    check_output_path(out, what="--out", inputs=[run_file], suffixes={"h5": HDF5_SUFFIXES, "csv": (".csv",)}.get(chosen, JSON_SUFFIXES))
    result = load_result(run_file)
    made = discretise(result, fraction=fraction, pauses=pauses)
    write_profiles(made, result, out, chosen)
    summary = made.summary() | {"format": chosen, "out": str(out)}
    if as_json:
        click.echo(json.dumps(_json_ready(summary)))
        return
    click.echo(f"fiberplan profiles: {run_file} -> {out} ({chosen})")
    limits = summary.pop("limits")
    _print_table(summary, ("positioners", "joints_moving", "segments_median", "segments_p95", "segments_max", "makespan_before_s",
                           "makespan_after_s", "discretise_s", "verified_ok", "collisions", "min_clearance_mm", "motor_violations"))
    click.echo("  limits applied: " + ", ".join(f"{k} = {v}" for k, v in limits.items() if v is not None and v is not False))
    unstated = [k for k, v in limits.items() if v is None]
    if unstated:
        click.echo(f"  not stated by the instrument (unconstrained): {', '.join(unstated)}")
    if summary["pauses"] or summary["creeps_mended"]:
        click.echo(f"  {summary['creeps_mended']} creep(s) mended, {summary['pauses']} pause(s) of everyone ({summary['pause_s']:.2f} s in all) "
                   "where a joint would creep, reverse without a stop or jump in speed (--no-pauses: leave them, reported)")
    if limits.get("ramp_time_s") is not None:
        settled = summary["ramp_pauses"]
        click.echo(f"  verified as the motors execute them too, each speed change ramped over {limits['ramp_time_s']:g} s "
                   "(makespan_after_s includes the last ramp)"
                   + (f"; {settled} stop(s) of a ramp where a ramp cut a corner" if settled else ""))
    if summary["source"] == "dechattered":
        click.echo(f"  fitted from the planned samples with their zigzags smoothed ({summary['dechattered_samples']} samples, verified)")
    if summary["source"] == "shortcut":
        click.echo(f"  back-and-forth of the positioners breaking a motor limit cut short where every pair stays clear "
                   f"({summary['shortcut_samples']} samples, verified)")
    if summary["followed_samples"]:
        click.echo(f"  positioners following their planned samples (narrower fits failed the verifier): {summary['followed_samples']}")
    if summary["motor_violations"]:
        click.echo(f"  {summary['motor_violations']} motor-limit violation(s) left where no allowed speed stays clear; "
                   f"list them with: fiberplan verify {out if chosen == 'h5' else '--paths ' + str(out)}", err=True)


@cli.command()
@click.argument("file", type=PATH)
@click.option("--out", type=PATH, required=True, help="PNG (or PDF/SVG) to write.")
@click.option("--time", "t", type=click.FloatRange(min=0.0), default=None, help="Instant to draw (s); default the first collision, else the end.")
@click.option("--profiles", "profile_ids", default=None, metavar="ID,ID",
              help="Draw these positioners' planned joint profiles against their motor profiles instead (made from FILE).")
def show(file: Path, out: Path, t: float | None, profile_ids: str | None) -> None:
    """Draw a snapshot of a run: arms, capsules, targets, collisions in red; or, with --profiles,
    chosen positioners' planned angles and speeds against their motor profiles."""
    check_output_path(out, what="--out", suffixes=IMAGE_SUFFIXES, inputs=[file])
    from fiberplan.plotting import default_snapshot_time, save_snapshot
    from fiberplan.trajectory import load_result
    from fiberplan.verify import verify as run_verify

    result = load_result(file)
    if profile_ids is not None:
        _show_profiles(result, file, out, profile_ids, t)
        return
    if t is None:
        report = run_verify(result.scenario, result.trajectory)
        t = default_snapshot_time(result, [c.t_first_s for c in report.collisions])
    save_snapshot(result, out, t)
    click.echo(f"wrote {out} (t = {t:.3f} s)")


@cli.command()
@click.argument("file", type=PATH)
@click.option("--out", type=PATH, required=True, help="HTML page to write (self-contained: open it in any browser, offline).")
def view(file: Path, out: Path) -> None:
    """Write an interactive viewer of a run: the focal plane with a time slider and play/pause,
    positioners coloured by outcome, hover/click for id, outcome and reason, search by id, the
    verifier's collisions and limit violations in red, a clicked positioner's joint angles."""
    check_output_path(out, what="--out", suffixes=(".html", ".htm"), inputs=[file])
    from fiberplan.trajectory import load_result
    from fiberplan.verify import verify as run_verify
    from fiberplan.viewer import frame_indices, write_viewer

    result = load_result(file)
    report = run_verify(result.scenario, result.trajectory)
    write_viewer(result, report, out)
    frames = len(frame_indices(len(result.trajectory.times), result.scenario.n_positioners))
    click.echo(f"wrote {out} ({result.scenario.n_positioners} positioners, {frames} of {len(result.trajectory.times)} samples as frames, "
               f"{out.stat().st_size / 1e6:.1f} MB; verified: {report.ok})")


@cli.command()
@click.argument("file", type=PATH)
@click.option("--out", type=PATH, required=True, help="GIF (or MP4 with ffmpeg) to write.")
@click.option("--fps", default=20, show_default=True, type=click.IntRange(1, 240), help="Frames per second.")
@click.option("--frames", default=120, show_default=True, type=click.IntRange(2, 10_000), help="Largest number of frames.")
def animate(file: Path, out: Path, fps: int, frames: int) -> None:
    """Animate a run."""
    check_output_path(out, what="--out", suffixes=ANIMATION_SUFFIXES, inputs=[file])
    from fiberplan.plotting import save_animation
    from fiberplan.trajectory import load_result

    result = load_result(file)
    save_animation(result, out, fps=fps, max_frames=frames)
    click.echo(f"wrote {out}")


@cli.command()
@click.option("--instrument", default="desi", show_default=True, help="Preset name (desi, moons, sdss) or instrument .toml file.")
@click.option("--positioners", "-n", default=500, show_default=True, type=POSITIONERS)
@click.option("--radius-mm", type=click.FloatRange(min=0, min_open=True), default=None)
@click.option("--kind", default="random", show_default=True, help="random, unfold, fold or clustered.")
@click.option("--seed", default=0, show_default=True, type=SEED)
@click.option("--min-start-clearance-mm", "min_start_clearance_mm", type=click.FloatRange(min=0), default=None,
              help="Smallest clearance between neighbours in a drawn start (default: the instrument's safety margin; 0: none).")
@click.option("--paf", "paf_file", type=PATH, default=None, help="Build the scenario from this ESO PAF fibre positioner configuration (MOONS).")
@click.option("--layout", "layout_file", type=PATH, default=None,
              help="Your focal plane: a CSV/ECSV table 'id, x_mm, y_mm, orient_deg[, locked]' (with --targets, or --kind and --seed).")
@click.option("--targets", "targets_file", type=PATH, default=None,
              help="With --paf: a target list 'id r_mm theta_deg L|R [priority]'; with --layout: a CSV/ECSV table "
                   "'id, x_mm, y_mm[, parity][, priority]' or 'id, alpha_deg, beta_deg[, priority]'.")
@click.option("--out", type=PATH, required=True, help="Scenario JSON file to write.")
@click.pass_context
def scenario(
    ctx: click.Context, instrument: str, positioners: int, radius_mm: float | None, kind: str, seed: int,
    min_start_clearance_mm: float | None, paf_file: Path | None, layout_file: Path | None, targets_file: Path | None, out: Path,
) -> None:
    """Generate a seeded scenario (on a hexagonal patch, or on your layout table), or read a layout
    and target table, or an instrument's PAF file and target list, and write it as JSON."""
    check_output_path(out, what="--out", suffixes=JSON_SUFFIXES, inputs=[paf_file, layout_file, targets_file])
    if paf_file is not None and layout_file is not None:
        raise click.UsageError("give --paf or --layout, not both (each gives the positioners)")
    if layout_file is not None:
        _scenario_on_layout(ctx, instrument, kind, seed, layout_file, targets_file, out, min_start_clearance_mm)
        return
    if paf_file is None:
        if targets_file is not None:
            raise click.UsageError("--targets needs --paf or --layout (the positioners the targets belong to)")
        from fiberplan.generate import make_scenario

        inst, preset, used = _instrument_arg(instrument)
        sc = make_scenario(inst, positioners, kind, seed, radius_mm=radius_mm, instrument_preset=preset,
                           min_start_clearance_mm=min_start_clearance_mm)
        sc.save(out)
        click.echo(f"wrote {out} ({sc.n_positioners} positioners, {sc.kind}, seed {sc.seed}, instrument {used})")
        return
    ignored = _explicit(ctx, "instrument", "positioners", "radius_mm", "kind", "seed", "min_start_clearance_mm")
    if ignored:
        raise click.UsageError(f"{', '.join(ignored)} cannot be used with --paf (the PAF file gives the instrument and positioners)")
    from fiberplan.paf import scenario_dict_from_paf
    from fiberplan.scenario import scenario_from_dict

    data, warnings = scenario_dict_from_paf(paf_file, targets_file)
    sc = scenario_from_dict(data, origin=f"PAF file {str(paf_file)!r}")
    _warn(warnings)
    if sc.infeasible:
        _warn([f"{len(sc.infeasible)} target(s) cannot be reached at all (they will hold): "
               + "; ".join(f"positioner {sc.ids[k]}: {why}" for k, why in list(sc.infeasible.items())[:10])])
    sc.save(out)
    click.echo(f"wrote {out} ({sc.n_positioners} positioners, {int(sc.wants_target.sum())} targets, {int(sc.locked.sum())} locked, "
               f"from {paf_file}{'' if targets_file is None else ' and ' + str(targets_file)})")


@cli.command()
@click.argument("name", required=False)
@click.option("--toml", "as_toml", is_flag=True, help="Print the instrument file itself (a complete file to copy and edit).")
def instruments(name: str | None, as_toml: bool) -> None:
    """List the instrument presets, or show one with the source of every number."""
    from fiberplan.instrument_io import instrument_text, load_instrument, preset_names

    if as_toml:
        if name is None:
            raise click.UsageError("--toml needs an instrument: fiberplan instruments NAME --toml")
        click.echo(instrument_text(name), nl=False)
        return
    if name is None:
        width = max(len(p) for p in preset_names())
        for preset in preset_names():
            click.echo(f"{preset:{width}s}  {load_instrument(preset).description}")
        return
    inst, _, used = _instrument_arg(name)
    click.echo(f"# {used}", err=True)
    if not inst.motors.stated:
        click.echo("# motor limits: none stated (unconstrained beyond the top speeds); add a [motors] table to state them", err=True)
    elif inst.motors.unstated():
        click.echo(f"# motor limits not stated (unconstrained): {', '.join(inst.motors.unstated())}", err=True)
    click.echo(json.dumps(inst.to_dict(), indent=2))


@cli.command()
@click.option("--settings", "settings_of", default=None, metavar="PLANNER", help="List every setting of this planner.")
@click.option("--instrument", default="desi", show_default=True, help="Instrument whose defaults --settings shows.")
@click.option("--json", "as_json", is_flag=True, help="With --settings: one JSON list.")
def planners(settings_of: str | None, instrument: str, as_json: bool) -> None:
    """List the registered planners, or one planner's settings with their values for an instrument."""
    from fiberplan.planners import make_settings, planner_names, settings_class
    from fiberplan.settings import describe_settings, setting_sources

    if settings_of is None:
        for name in planner_names():
            click.echo(name)
        return
    inst, _, used = _instrument_arg(instrument)
    rows = describe_settings(make_settings(settings_of, inst), setting_sources(settings_class(settings_of), inst, settings_of))
    if as_json:
        click.echo(json.dumps(_json_ready(rows)))
        return
    click.echo(f"{settings_of} settings for instrument {inst.name} ({used}); change with --set KEY=VALUE")
    click.echo("  (source: default = the planner's own, instrument = scaled to its motors, instrument file = [planner_defaults])")
    group = None
    width = max(len(r["name"]) for r in rows)
    order = {g: k for k, g in enumerate(dict.fromkeys(r["group"] for r in rows))}
    for row in sorted(rows, key=lambda r: order[r["group"]]):
        if row["group"] != group:
            group = row["group"]
            click.echo(f"[{group}]")
        value = json.dumps(_json_ready(row["value"]))
        unit = f" {row['unit']}" if row["unit"] else ""
        click.echo(f"  {row['name']:<{width}}  {value}{unit}  [{row['source']}] ({row['range']}): {row['doc']}")


@cli.command()
@click.argument("spec", type=PATH)
@click.option("--scheduler", default=None, help="Address of a Dask distributed scheduler (default: a local process pool).")
@click.option("--workers", type=int, default=None, help="Local worker processes (default: all cores).")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
def sweep(spec: Path, scheduler: str | None, workers: int | None, quiet: bool) -> None:
    """Run a study file: every grid cell x seed, results in a Parquet table.

    Re-running the same command after an interruption skips the finished runs.
    """
    from fiberplan.studies import load_study, recorded_tasks, run_study

    study = load_study(spec)
    check_output_path(study.out, what=f"study {str(spec)!r}: out", suffixes=PARQUET_SUFFIXES, inputs=[spec])
    already = len(recorded_tasks(study))
    click.echo(f"study {study.name}: {len(study.tasks)} runs, {already} already done -> {study.out}", err=True)
    rows = run_study(study, workers=workers, scheduler=scheduler, progress=not quiet)
    import pandas as pd

    table = pd.read_parquet(study.out)
    errors = int((table["status"] == "error").sum())
    lost = int((table["status"] == "lost").sum())
    click.echo(f"wrote {study.out}: {rows} runs ({errors} with errors, {lost} lost to the machinery)")
    if lost:
        raise InfrastructureError(f"{lost} run(s) were lost to dead workers after retries; run the same command again to retry them")


@cli.command("study-plot")
@click.argument("results", type=PATH)
@click.option("--kind", type=click.Choice(["rates", "scaling", "makespan"]), default="rates", show_default=True)
@click.option("--x", "x", default="n_positioners", show_default=True, help="Column on the x axis (rates).")
@click.option("--by", default="planner", show_default=True, help="Column separating curves / boxes.")
@click.option("--rate", type=click.Choice(["deadlock", "success"]), default="deadlock", show_default=True)
@click.option("--out", type=PATH, required=True, help="Image to write.")
def study_plot(results: Path, kind: str, x: str, by: str, rate: str, out: Path) -> None:
    """Plot a study table: rates with error bars, plan time vs N, or makespan / lower bound."""
    check_output_path(out, what="--out", suffixes=IMAGE_SUFFIXES, inputs=[results])
    from fiberplan.plotting import plot_makespan_ratio, plot_rates, plot_scaling, save_figure
    from fiberplan.studies import StudyError, load_results, rates

    frame = load_results(results)
    for column in (x, by) if kind == "rates" else (by,):
        if column not in frame.columns:
            raise StudyError(f"{results}: no column {column!r}; columns are {', '.join(map(str, frame.columns))}")
    if kind == "rates":
        fig = plot_rates(rates(frame, [x, by]), x, hue=by, rate=rate)
    elif kind == "scaling":
        fig = plot_scaling(frame, hue=by)
    else:
        fig = plot_makespan_ratio(frame, by=by)
    save_figure(fig, out)
    click.echo(f"wrote {out}")


@cli.command()
@click.option("--instrument", default="desi", show_default=True, help="Preset name (desi, moons, sdss) or instrument .toml file.")
@click.option("--positioners", "-n", default=7, show_default=True, type=POSITIONERS, help="Positioners in the hexagonal group.")
@click.option(
    "--scenario-kind", default="hard", show_default=True, help="hard (clustered starts and targets), random, unfold, fold or clustered."
)
@click.option("--seeds", default=5, show_default=True, type=click.IntRange(1, 100_000), help="Run seeds 0..K-1.")
@click.option("--seed-list", default=None, help="Comma-separated seeds (instead of --seeds).")
@click.option("--planners", "planner_list", default="central,mpc,dnf", show_default=True, help="Comma-separated planner names.")
@click.option("--set", "settings", multiple=True, metavar="PLANNER.KEY=VALUE", help="Setting override of one planner (repeatable).")
@click.option(
    "--energy-gap", is_flag=True, help="Also solve central in energy mode at each planner's makespan (central may be left out of --planners)."
)
@click.option("--out", type=PATH, default=Path("compare.parquet"), show_default=True, help="Parquet file of the rows.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object (rows and aggregates) instead of the table.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
def compare(
    instrument: str, positioners: int, scenario_kind: str, seeds: int, seed_list: str | None, planner_list: str,
    settings: tuple[str, ...], energy_gap: bool, out: Path, as_json: bool, quiet: bool,
) -> None:
    """Run several planners on the same seeded scenarios; verify each; one row per planner x scenario."""
    check_output_path(out, what="--out", suffixes=PARQUET_SUFFIXES)
    from tqdm import tqdm

    from fiberplan.studies import format_table, run_compare, write_parquet

    if seed_list is not None:
        try:
            seed_values = [int(s) for s in seed_list.split(",") if s.strip()]
        except ValueError as e:
            raise click.BadParameter(f"expected comma-separated integers, found {seed_list!r}", param_hint="--seed-list") from e
        bad = [v for v in seed_values if not 0 <= v <= MAX_SEED]
        if bad:
            raise click.BadParameter(f"seeds must lie in [0, 2**63 - 1], found {bad[0]}", param_hint="--seed-list")
    else:
        seed_values = list(range(seeds))
    if not seed_values:
        raise click.BadParameter("no seeds given", param_hint="--seed-list")
    names = [p.strip() for p in planner_list.split(",") if p.strip()]
    per_planner: dict[str, dict[str, Any]] = {}
    for key, value in _parse_settings(settings).items():
        if "." not in key:
            raise click.BadParameter(f"expected PLANNER.KEY=VALUE, found {key!r}", param_hint="--set")
        planner_name, setting = key.split(".", 1)
        per_planner.setdefault(planner_name, {})[setting] = value
    runs = len(names) + (sum(name != "central" for name in names) if energy_gap else 0)  # (the energy references count too)
    bar = tqdm(total=len(seed_values) * runs, desc="compare", disable=True if quiet else None, file=sys.stderr, leave=False)

    def progress(label: str) -> None:
        bar.set_postfix_str(label)
        bar.update(1)

    try:
        result = run_compare(
            instrument, positioners, names, seed_values, kind=scenario_kind, settings=per_planner, energy_gap=energy_gap, progress=progress
        )
    finally:
        bar.close()
    write_parquet(result.rows, out)
    if as_json:
        click.echo(json.dumps(result.to_dict() | {"out": str(out)}))
    else:
        click.echo(format_table(result))
        click.echo(f"wrote {out}")


def main(argv: Sequence[str] | None = None) -> None:
    """Entry point: run the CLI, turning fiberplan errors into one line and exit status 2."""
    try:
        cli.main(args=list(argv) if argv is not None else None, prog_name="fiberplan", standalone_mode=False)
    except click.exceptions.Abort:
        click.echo("aborted", err=True)
        sys.exit(130)
    except click.ClickException as e:
        # One line, whatever click would have printed (usage, hint, message).
        command = f" {e.ctx.command_path.split(' ', 1)[1]}" if isinstance(e, click.UsageError) and e.ctx and " " in e.ctx.command_path else ""
        hint = f" (see fiberplan{command} --help)" if isinstance(e, click.UsageError) else ""
        click.echo(f"fiberplan: error: {e.format_message()}{hint}", err=True)
        sys.exit(e.exit_code)
    except InfrastructureError as e:
        click.echo(f"fiberplan: error: {e}", err=True)
        sys.exit(EXIT_INFRASTRUCTURE)
    except FiberplanError as e:
        click.echo(f"fiberplan: error: {e}", err=True)
        sys.exit(2)
    except OSError as e:
        click.echo(f"fiberplan: error: {e.strerror or e}: {e.filename or ''}".rstrip(": "), err=True)
        sys.exit(2)
    except KeyboardInterrupt:
        click.echo("interrupted", err=True)
        sys.exit(130)
    except MemoryError:
        click.echo("fiberplan: error: out of memory; plan fewer positioners or a shorter run", err=True)
        sys.exit(2)
    except Exception as e:
        if os.environ.get("FIBERPLAN_DEBUG"):
            raise
        click.echo(f"fiberplan: internal error: {type(e).__name__}: {e} (a bug: please report it; FIBERPLAN_DEBUG=1 shows the traceback)",
                   err=True)
        sys.exit(EXIT_INTERNAL)


if __name__ == "__main__":
    main()
