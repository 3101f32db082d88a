"""`bruce-eval transfer`: the paper's sim-to-real experiments (§IV-C, Figs. 6-10), rehearsed in the mock.

The nominal mock is "the simulator", the mock with a reality-gap profile (`configs/gaps/`) "the robot". Every
experiment (`EXPERIMENTS`: tracking, circle, reverse, turn) runs the same nominal controller on the same command
schedule once in the nominal mock, the reference, and on the gapped mock under each transfer mode, once per gap
seed; the sweeps vary the actuator latency and the Eq. 9 gains. Runs are scored on the simulator's truth after the
start-up transient and up to a fall (`run_metrics`). Output: DIR/transfer.json (with the acceptance of
`training.evaluation.transfer_acceptance`), DIR/transfer.md and figures; each run is cached under DIR/runs
(`training.evaluation.transfer_cache`), so an interrupted suite resumes. Experiments, metrics and the output's
layout: docs/transfer.md ("The rehearsal").
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

from bruce_hw.config import DEFAULT_CONFIG, ConfigError, resolve_config_path
from bruce_hw.reality_gap import GapError, RealityGap, latency_ticks, load_gap
from runtime.control.policy_spec import policy_spec_for
from runtime.loop.observers import TRACKING_SKIP_S
from runtime.robot_config import load_config
from runtime.transfer.reference_models import REFERENCE_MODELS
from runtime.transfer.registry import listed_schemes, scheme_names
from training.evaluation.report import json_safe
from training.evaluation.transfer_acceptance import (
    ONE_FACTOR_PROFILES,
    acceptance,
    latency_tolerance,
    recommended,
)
from training.evaluation.transfer_cache import RunCache, spec_key, trace
from training.evaluation.transfer_metrics import aggregate, run_metrics
from training.evaluation.transfer_report import markdown, plot, suite_markdown
from training.evaluation.transfer_runs import (
    EXPERIMENTS,
    LOOKAHEAD_MODE,
    MODES,
    PERFECT_MODEL_SUFFIX,
    Experiment,
    RunRecord,
    RunSpec,
    run_one,
    scheme_of,
)
from training.executor import Executor, ExecutorError, add_executor_arguments, job_files, make_executor

DEFAULT_SECONDS = 20.0
DEFAULT_LATENCIES_MS = (0.0, 2.0, 4.0, 6.0, 8.0, 10.0)
DEFAULT_GAIN_SCALES = (0.0, 0.25, 0.5, 1.0, 2.0, 4.0)
# Named lists of profiles (--suite): issue 20's acceptance needs `default` (its bars), `none` (the null test) and the
# one-factor profiles; `mild` and `harsh` bracket `default`.
SUITES = {"acceptance": ("default", "none", *ONE_FACTOR_PROFILES, "mild", "harsh")}


class TransferError(ValueError):
    """A transfer evaluation that cannot run as asked; the message names the option."""


# -- the evaluation --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TransferSettings:
    gap: RealityGap
    gap_name: str
    seeds: tuple[int, ...] = (0, 1, 2)
    seconds: float = DEFAULT_SECONDS
    controller: str = "policy"
    estimator: str = "kinematic"
    experiments: tuple[str, ...] = tuple(e.name for e in EXPERIMENTS)
    latencies_ms: tuple[float, ...] = DEFAULT_LATENCIES_MS
    gain_scales: tuple[float, ...] = DEFAULT_GAIN_SCALES
    sweep_seeds: tuple[int, ...] = (0, 1)
    jobs: int = 1
    config: str | None = None
    lookahead: int | str | None = "auto"  # ticks, "auto" (the gap's latency), or None: no look-ahead variant
    schemes: tuple[str, ...] | None = None  # modes to run besides direct (None: Eq. 9 and its look-ahead variant)
    overrides: tuple[str, ...] = ()
    profiles: tuple[tuple[str, RealityGap], ...] = ()  # (name, gap) of every profile; (): gap_name, gap alone

    def per_profile(self) -> list[TransferSettings]:
        """The settings of each profile on its own; the sweeps run on the first profile only."""
        profiles = self.profiles or ((self.gap_name, self.gap),)
        return [dataclasses.replace(self, gap=gap, gap_name=name, profiles=(),
                                    **({} if i == 0 else {"latencies_ms": (), "gain_scales": ()}))
                for i, (name, gap) in enumerate(profiles)]

    @property
    def modes(self) -> tuple[str, ...]:
        if self.schemes is not None:
            return ("direct", *(m for m in self.schemes if m != "direct"))
        return MODES + ((LOOKAHEAD_MODE,) if self.lookahead is not None else ())


def lookahead_ticks(setting: int | str, gap: RealityGap, dt: float = 1e-3) -> int:
    """The look-ahead variant's ticks: a number as given, or "auto": the ticks between reading the joints and the
    torque acting on them that the gap adds (actuator plus sensor latency)."""
    if setting != "auto":
        return int(setting)
    return latency_ticks(gap.actuator_latency_s, dt) + latency_ticks(gap.sensor_latency_s, dt)


def _spec(settings: TransferSettings, experiment: Experiment, mode: str, seed: int | None,
          gap: RealityGap | None = None, **changes) -> RunSpec:
    if mode != "nominal":
        gap = dataclasses.replace(gap or settings.gap, seed=seed)
    if mode == LOOKAHEAD_MODE:
        changes["lookahead"] = lookahead_ticks(settings.lookahead, gap)
    return RunSpec(experiment=experiment.name, command=experiment.command, seconds=settings.seconds, mode=mode,
                   gap=None if mode == "nominal" else gap, controller=settings.controller,
                   estimator=settings.estimator, config=settings.config, overrides=settings.overrides, **changes)


def _sweep_gap(gap: RealityGap, latency_ms: float) -> RealityGap:
    return dataclasses.replace(gap, actuator_latency_s=latency_ms / 1000.0)


EXPERIMENT_BY_NAME = {e.name: e for e in EXPERIMENTS}


def _latency_specs(settings: TransferSettings, latency_ms: float, mode: str) -> list[RunSpec]:
    """The latency sweep's runs of `mode` at `latency_ms`: the tracking command, one per sweep seed."""
    return [dataclasses.replace(_spec(settings, EXPERIMENT_BY_NAME["tracking"], mode, seed,
                                      gap=_sweep_gap(settings.gap, latency_ms)), experiment="sweep_latency")
            for seed in settings.sweep_seeds]


def _gain_specs(settings: TransferSettings, scale: float) -> list[RunSpec]:
    return [dataclasses.replace(_spec(settings, EXPERIMENT_BY_NAME["tracking"], "pinn", seed, eq9_scale=scale),
                                experiment="sweep_gain") for seed in settings.sweep_seeds]


def plan(settings: TransferSettings) -> list[RunSpec]:
    """Every run the evaluation of one profile needs, in a fixed order: per experiment the nominal run, then each
    mode per seed; then the latency sweep and the Eq. 9 gain sweep on the tracking command."""
    specs = []
    for name in settings.experiments:
        experiment = EXPERIMENT_BY_NAME[name]
        specs.append(_spec(settings, experiment, "nominal", None))
        specs += [_spec(settings, experiment, mode, seed) for mode in settings.modes for seed in settings.seeds]
    if "tracking" not in settings.experiments and (settings.latencies_ms or settings.gain_scales):
        specs.append(_spec(settings, EXPERIMENT_BY_NAME["tracking"], "nominal", None))
    for latency in settings.latencies_ms:
        for mode in settings.modes:
            specs += _latency_specs(settings, latency, mode)
    for scale in settings.gain_scales if "pinn" in settings.modes else ():
        specs += _gain_specs(settings, scale)
    return specs


def plan_suite(settings: TransferSettings) -> list[RunSpec]:
    """Every run of every profile (the nominal runs, shared, appear once per profile; `execute` runs them once)."""
    return [spec for profile in settings.per_profile() for spec in plan(profile)]


def nominal_of(spec: RunSpec) -> RunSpec:
    """The nominal run `spec` is scored against (a sweep's: the tracking experiment's)."""
    name = spec.experiment if spec.experiment in EXPERIMENT_BY_NAME else "tracking"
    return dataclasses.replace(spec, experiment=name, mode="nominal", gap=None, eq9_scale=1.0, lookahead=0)


@dataclass
class RunResults:
    """Every run's metrics against its nominal reference, and the records kept (the nominal references whole, the
    runs the figures draw as traces), by `spec_key`."""

    metrics: dict[str, dict] = field(default_factory=dict)
    records: dict[str, RunRecord] = field(default_factory=dict)

    def of(self, spec: RunSpec) -> dict:
        return self.metrics[spec_key(spec)]

    def record(self, spec: RunSpec) -> RunRecord | None:
        return self.records.get(spec_key(spec))


def _run_scored(spec: RunSpec, reference: RunRecord | None, kept: bool) -> tuple[dict, RunRecord | None]:
    """Run `spec` and score it against `reference`, its nominal run's record (None when `spec` is nominal: itself).
    Returns the metrics and, when `kept`, the record (a nominal one whole, any other as a figure trace)."""
    record = run_one(spec)
    if spec.mode == "nominal":
        reference = record
    metrics = run_metrics(record, reference, EXPERIMENT_BY_NAME[nominal_of(spec).experiment])
    return metrics, (record if spec.mode == "nominal" else trace(record)) if kept else None


def _profile_label(spec: RunSpec) -> str:
    return "no gap" if spec.gap is None else Path(spec.gap.source).stem


def shipped_files(specs: list[RunSpec]) -> list[Path]:
    """What the runs of `specs` read from disk (`job_files` of each)."""
    return sorted(set().union(*(job_files(resolve_config_path(spec.config or DEFAULT_CONFIG), spec.overrides)
                                for spec in specs)))


def _as_shipped(spec: RunSpec, executor: Executor) -> RunSpec:
    """`spec` with its files named as the executor's workers read them (the same files, shipped)."""
    config, overrides = executor.shipped_config(resolve_config_path(spec.config or DEFAULT_CONFIG), spec.overrides)
    return dataclasses.replace(spec, config=config, overrides=tuple(overrides))


def execute(specs: list[RunSpec], out: Path, executor: Executor, keep: list[RunSpec] = (),
            progress: bool = True) -> RunResults:
    """Run every distinct spec once (the nominal references first) on `executor`, each run's metrics (and the
    records kept: nominal runs and `keep`) cached under OUT/runs as it finishes (`transfer_cache`); what the cache
    already holds is not run again."""
    cache = RunCache(Path(out) / "runs")
    unique: dict[str, RunSpec] = {}
    for spec in specs:
        unique.setdefault(spec_key(spec), spec)
    for spec in list(unique.values()):
        unique.setdefault(spec_key(nominal_of(spec)), nominal_of(spec))
    kept = {spec_key(s) for s in keep} | {k for k, s in unique.items() if s.mode == "nominal"}
    results = RunResults()
    done = 0

    def report(spec: RunSpec, how: str) -> None:
        if progress:
            print(f"bruce-eval transfer: {done}/{len(unique)} {spec.experiment} {spec.mode} "
                  f"({_profile_label(spec)}){how}", file=sys.stderr)

    for stage in (lambda s: s.mode == "nominal", lambda s: s.mode != "nominal"):
        todo = []
        for key, spec in ((k, s) for k, s in unique.items() if stage(s)):
            metrics = cache.metrics(key)
            record = cache.record(key, spec, RunRecord) if key in kept and metrics is not None else None
            if metrics is not None and (record is not None or key not in kept):
                results.metrics[key] = metrics
                if record is not None:
                    results.records[key] = record
                done += 1
                report(spec, " cached")
            else:
                todo.append((key, spec))
        references: dict[str, object] = {}  # each nominal record sent to the workers once
        calls = []
        for key, spec in todo:
            reference = None
            if spec.mode != "nominal":
                nominal = spec_key(nominal_of(spec))
                if nominal not in references:
                    references[nominal] = executor.share(results.records[nominal])
                reference = references[nominal]
            calls.append((_as_shipped(spec, executor), reference, key in kept))
        for index, (metrics, record) in executor.map(_run_scored, calls):
            key, spec = todo[index]
            cache.save_metrics(key, spec, metrics)
            results.metrics[key] = cache.metrics(key)  # as a resumed run reads it back (NaN -> None)
            if record is not None:
                record = dataclasses.replace(record, spec=spec)  # named as here, not as a worker read it
                cache.save_record(key, record)
                results.records[key] = record
            done += 1
            report(spec, "")
    return results


def evaluate(settings: TransferSettings, results: RunResults) -> tuple[dict, dict]:
    """(report, traces) of one profile: per experiment and mode the metrics aggregated over seeds, plus the nominal
    run's own; the sweeps with each mode's latency tolerance; the records the figures draw."""
    report: dict = {}
    traces: dict = {}
    for name in settings.experiments:
        experiment = EXPERIMENT_BY_NAME[name]
        nominal = _spec(settings, experiment, "nominal", None)
        entry = {"command": list(experiment.command), "seconds": settings.seconds, "nominal": results.of(nominal)}
        traces[name] = {"nominal": results.record(nominal)}
        for mode in settings.modes:
            specs = [_spec(settings, experiment, mode, seed) for seed in settings.seeds]
            entry[mode] = aggregate([results.of(spec) for spec in specs])
            traces[name][mode] = results.record(specs[0])
        direct = entry["direct"]
        for mode in settings.modes[1:]:
            entry[f"{mode}_over_direct"] = {
                key: (entry[mode][key] / direct[key] if direct[key] else float("nan"))
                for key in ("joint_rmse", "mean_radial_deviation", "mean_deviation_from_simulator", "drift")
                if key in direct and direct[key] is not None and entry[mode].get(key) is not None}
        report[name] = entry
    sweeps: dict = {"latency": [], "eq9_gain": []}
    for latency in settings.latencies_ms:
        row = {"latency_ms": latency}
        for mode in settings.modes:
            specs = _latency_specs(settings, latency, mode)
            metrics = aggregate([results.of(spec) for spec in specs])
            row[mode] = {"joint_rmse": metrics["joint_rmse"], "falls": metrics["falls"], "seeds": metrics["seeds"]}
            if mode == LOOKAHEAD_MODE:
                row[mode]["lookahead_ticks"] = specs[0].lookahead
        sweeps["latency"].append(row)
    if sweeps["latency"]:
        sweeps["latency_tolerance_ms"] = {mode: latency_tolerance(sweeps["latency"], mode) for mode in settings.modes}
    for scale in settings.gain_scales if "pinn" in settings.modes else ():
        metrics = aggregate([results.of(spec) for spec in _gain_specs(settings, scale)])
        sweeps["eq9_gain"].append({"scale": scale, "pinn": {"joint_rmse": metrics["joint_rmse"],
                                                           "falls": metrics["falls"], "seeds": metrics["seeds"]}})
    # Eq. 8 alone does not depend on the Eq. 9 gains
    sweeps["eq9_gain_direct_reference"] = report["tracking"]["direct"]["joint_rmse"] if "tracking" in report else None
    report["sweeps"] = sweeps
    return report, traces


def _numbers(text: str, option: str) -> tuple[float, ...]:
    try:
        return tuple(float(v) for v in text.split(",") if v.strip()) if text.strip() else ()
    except ValueError:
        raise TransferError(f"{option}: expected comma-separated numbers, got {text!r}") from None


def add_parser(commands) -> argparse.ArgumentParser:
    p = commands.add_parser("transfer", help="sim-to-real rehearsal: direct vs PINN transfer on a gapped mock",
                            description=__doc__.split("\n\n")[0])
    p.add_argument("--gap", default=None,
                   help="reality-gap profile: a name in configs/gaps or a YAML path, or several, comma-separated: "
                        "each is evaluated, the sweeps on the first (default: default)")
    p.add_argument("--suite", choices=sorted(SUITES), default=None,
                   help="a named list of profiles instead of --gap: " + "; ".join(
                       f"{name} = {','.join(profiles)}" for name, profiles in SUITES.items()))
    p.add_argument("--out", type=Path, required=True, help="directory for transfer.json, transfer.md and PNGs")
    p.add_argument("--seeds", default="0,1,2", help="gap noise seeds per mode (default: %(default)s)")
    p.add_argument("--seconds", type=float, default=DEFAULT_SECONDS, help="per run (default: %(default)s)")
    p.add_argument("--controller", choices=("policy", "teacher"), default="policy",
                   help="nominal controller (default: the committed policy)")
    p.add_argument("--estimator", choices=("kinematic", "truth"), default="kinematic",
                   help="base state for every controller and scheme: kinematic (default; robot-faithful): IMU + leg "
                        "kinematics + contact switches on the gapped sensors, as on the robot, and the twin "
                        "resynchronised from that estimate; truth: the simulator's truth (a diagnostic: no robot "
                        "has it)")
    p.add_argument("--experiments", default=",".join(e.name for e in EXPERIMENTS),
                   help="subset of %(default)s")
    p.add_argument("--latencies-ms", default=",".join(f"{v:g}" for v in DEFAULT_LATENCIES_MS),
                   help="actuator latency sweep, '' to skip (default: %(default)s)")
    p.add_argument("--gain-scales", default=",".join(f"{v:g}" for v in DEFAULT_GAIN_SCALES),
                   help="Eq. 9 gain sweep, '' to skip (default: %(default)s)")
    p.add_argument("--sweep-seeds", default="0,1", help="gap noise seeds per sweep point (default: %(default)s)")
    p.add_argument("--lookahead", default="auto",
                   help="the look-ahead variant's extra PINN ticks: N, 'auto' (the gap's actuator + sensor latency) "
                        "or 'off' (default: %(default)s)")
    p.add_argument("--schemes", default=None,
                   help=f"comma-separated modes to compare with direct transfer: transfer schemes ({listed_schemes()}) "
                        f"and SCHEME{PERFECT_MODEL_SUFFIX} for a scheme's perfect-model control (default: pinn and its "
                        "look-ahead variant)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="robot config override for every run, e.g. transfer.observer.time_constant_s=0.5 (repeatable)")
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1,
                   help="parallel runs with --executor local (default: CPU count)")
    add_executor_arguments(p)
    p.add_argument("--config", default=None, help="robot config (default: BRUCE's)")
    return p


def profiles_from_args(args) -> tuple[tuple[str, RealityGap], ...]:
    """(name, gap) of each profile of --gap or --suite, in order."""
    suite, gaps = getattr(args, "suite", None), getattr(args, "gap", None)
    if suite is not None and gaps is not None:
        raise TransferError("--gap and --suite: give one (a suite is a list of profiles)")
    names = SUITES[suite] if suite is not None else tuple(n.strip() for n in (gaps or "default").split(","))
    if not all(names):
        raise TransferError(f"--gap: an empty profile name in {gaps!r}")
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise TransferError(f"--gap: {twice[0]!r} given twice")
    return tuple((name, load_gap(name)) for name in names)


def settings_from_args(args) -> TransferSettings:
    names = tuple(n.strip() for n in args.experiments.split(",") if n.strip())
    known = {e.name for e in EXPERIMENTS}
    unknown = [n for n in names if n not in known]
    if unknown or not names:
        raise TransferError(f"--experiments: {unknown or names!r} not among {sorted(known)}")
    seeds = tuple(int(s) for s in _numbers(args.seeds, "--seeds"))
    sweep_seeds = tuple(int(s) for s in _numbers(args.sweep_seeds, "--sweep-seeds"))
    if not seeds:
        raise TransferError("--seeds: at least one seed")
    if not args.seconds > TRACKING_SKIP_S:
        raise TransferError(f"--seconds: must exceed the {TRACKING_SKIP_S:g} s start-up that is not scored")
    latencies, scales = _numbers(args.latencies_ms, "--latencies-ms"), _numbers(args.gain_scales, "--gain-scales")
    if (latencies or scales) and not sweep_seeds:
        raise TransferError("--sweep-seeds: at least one seed when sweeping")
    lookahead: int | str | None = args.lookahead
    if lookahead == "off":
        lookahead = None
    elif lookahead != "auto":
        try:
            lookahead = int(lookahead)
        except ValueError:
            raise TransferError(f"--lookahead: expected ticks >= 1, 'auto' or 'off', got {args.lookahead!r}") from None
        if lookahead < 1:
            raise TransferError(f"--lookahead: expected ticks >= 1, 'auto' or 'off', got {args.lookahead!r}")
    schemes = None
    if getattr(args, "schemes", None) is not None:
        schemes = tuple(m.strip() for m in args.schemes.split(",") if m.strip())
        for mode in schemes:
            scheme, model = scheme_of(mode)
            if scheme not in scheme_names() or model not in (None, *REFERENCE_MODELS):
                raise TransferError(f"--schemes: {mode!r}: expected SCHEME or SCHEME@MODEL with SCHEME one of "
                                    f"{', '.join(scheme_names())} and MODEL one of {', '.join(REFERENCE_MODELS)}")
    overrides = tuple(getattr(args, "overrides", None) or ())
    if overrides:
        overridden = load_config(args.config or DEFAULT_CONFIG, list(overrides))  # a bad --set fails here
        policy = overridden.models.policy
        if policy is not None and not Path(policy).is_file():  # before the worker processes, which would raise
            raise TransferError(f"--set policy.model: {policy}: policy file not found")
        if policy is not None:
            policy_spec_for(overridden, Path(policy))  # a bad spec is one line here, not a worker's traceback
    profiles = profiles_from_args(args)
    return TransferSettings(gap=profiles[0][1], gap_name=profiles[0][0], profiles=profiles, lookahead=lookahead,
                            seeds=seeds, schemes=schemes, overrides=overrides,
                            seconds=args.seconds,
                            controller=args.controller, estimator=args.estimator, experiments=names,
                            latencies_ms=latencies, gain_scales=scales, sweep_seeds=sweep_seeds,
                            jobs=max(1, args.jobs), config=args.config)


def run_transfer(args, argv: list[str]) -> int:
    try:
        settings = settings_from_args(args)
        config = load_config(settings.config) if settings.config else load_config()
    except (TransferError, GapError, ConfigError) as exc:
        print(f"bruce-eval: error: {exc}", file=sys.stderr)
        return 1
    profiles = settings.per_profile()
    first = profiles[0]
    figure_runs = [_spec(first, EXPERIMENT_BY_NAME[name], mode, first.seeds[0]) for name in first.experiments
                   for mode in first.modes]
    args.out.mkdir(parents=True, exist_ok=True)
    specs = plan_suite(settings)
    try:
        with make_executor(args, settings.jobs, ship=shipped_files(specs)) as executor:
            results = execute(specs, args.out, executor, keep=figure_runs)
    except ExecutorError as exc:
        print(f"bruce-eval: error: {exc}", file=sys.stderr)
        return 1
    reports = {profile.gap_name: evaluate(profile, results)[0] for profile in profiles[1:]}
    report, traces = evaluate(first, results)
    reports = {first.gap_name: report, **reports}
    meta = {"command": "bruce-eval " + " ".join(argv), "gap_name": settings.gap_name, "profiles": list(reports),
            "gap": {k: v for k, v in dataclasses.asdict(settings.gap).items()}, "controller": settings.controller,
            "estimator": settings.estimator, "seconds": settings.seconds, "seeds": list(settings.seeds),
            "sweep_seeds": list(settings.sweep_seeds), "joints": list(config.joints),
            "lookahead": None if settings.lookahead is None else (
                f"auto ({lookahead_ticks('auto', settings.gap)})" if settings.lookahead == "auto"
                else settings.lookahead),
            "scored_after_s": TRACKING_SKIP_S, "modes": list(settings.modes), "overrides": list(settings.overrides)}
    table = acceptance(reports, settings.modes, settings.estimator)
    document = {"meta": meta, "recommended": recommended(table), "acceptance": table, **report}
    if len(reports) > 1:
        document["profiles"] = reports
    (args.out / "transfer.json").write_text(json.dumps(json_safe(document), indent=2) + "\n")
    text = markdown(report, meta) + "\n" + suite_markdown(reports, settings.modes, table, settings.estimator)
    (args.out / "transfer.md").write_text(text)
    try:
        figures = plot(args.out, report, traces, tuple(config.joints))
    except ModuleNotFoundError as exc:  # matplotlib comes with the `train` extra; the numbers do not need it
        figures = [f"no figures ({exc.name} is not installed: pip install -e '.[train]')"]
    print(text)
    print(f"bruce-eval: wrote {args.out}/transfer.json, transfer.md, {', '.join(figures)}")
    return 0
