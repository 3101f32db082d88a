"""The acceptance of a transfer scheme, checked on `bruce-eval transfer`'s per-profile reports.

`acceptance(...)[mode][bar]` = value, limit, pass, for every bar the evaluation has data for: tracking, circle and
no new falls on the bar profile, `none`, each one-factor profile that ran, and the latency tolerated in the sweep.
`recommended` names the mode that passes every bar it has, tracking and circle included, with the best tracking;
never direct, Eq. 9 (the paper's row) or a perfect-model control (SCHEME@nominal). The bars: docs/transfer.md
("The acceptance and `recommended`").
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Bars:
    """The shares of direct transfer's figures a recommended scheme must stay within on the bar profile."""

    issue: int
    tracking: float   # tracking joint RMSE at most this share of direct's ...
    circle: float     # ... the circle's deviation from the simulator's path at most this share


# Per estimator: a robot-faithful rehearsal (issue 33: what a lab gets on its robot) and the truth-fed diagnostic
# (issue 20's bars, kept with the diagnostic they were set on).
BARS = {"kinematic": Bars(issue=33, tracking=0.25, circle=0.75), "truth": Bars(issue=20, tracking=0.5, circle=0.6)}
MIN_SEEDS = 3        # ... over at least this many gap seeds
NULL_RMSE = 0.01     # rad: on `none`, a scheme may move the joints this far off the simulator's
BAR_PROFILE = "default"
NULL_PROFILE = "none"
# The shipped profiles that are `none` plus one factor (configs/gaps/).
ONE_FACTOR_PROFILES = ("latency_2ms", "torque_lag_2ms", "torque_constant_0p8", "coulomb_0p2", "viscous_0p05",
                       "mass_1p2", "sensor_noise_1ms", "armature_add_1bear", "contact_delay_bounce",
                       "imu_latency_3ms", "encoder_quantisation")
EXPERIMENTS_BARRED = ("tracking", "circle")
NOT_CANDIDATES = ("direct", "pinn", "eq9", "pinn_ahead")  # Eq. 8 alone, Eq. 9 and its look-ahead variant


def is_candidate(mode: str) -> bool:
    """Whether `mode` may be recommended: a scheme of its own on the configured model."""
    return mode not in NOT_CANDIDATES and "@" not in mode


def latency_tolerance(rows: list[dict], mode: str) -> float | None:
    """The largest swept actuator latency (ms) up to which `mode` never fell, on any seed, nor at any smaller
    latency; None when it fell at the smallest."""
    tolerated = None
    for row in sorted(rows, key=lambda r: r["latency_ms"]):
        if mode not in row or row[mode]["falls"]:
            break
        tolerated = row["latency_ms"]
    return tolerated


def _bar(value, limit, passed: bool, **about) -> dict:
    return {"value": value, "limit": limit, "pass": bool(passed), **about}


def _at_most(value, limit) -> bool:
    return value is not None and limit is not None and math.isfinite(value) and value <= limit


def _new_falls(entry: dict, mode: str) -> int:
    """Seeds on which `mode` fell and direct did not (seeds in the same order in both)."""
    mode_seeds, direct_seeds = entry[mode].get("per_seed"), entry["direct"].get("per_seed")
    if mode_seeds is None or direct_seeds is None:
        return max(0, entry[mode]["falls"] - entry["direct"]["falls"])
    return sum(m["fell"] and not d["fell"] for m, d in zip(mode_seeds, direct_seeds, strict=True))


def _seeds(seeds: int) -> dict:
    return {"seeds": seeds} if seeds >= MIN_SEEDS else {"seeds": seeds, "note": f"needs >= {MIN_SEEDS} gap seeds"}


def _ratio_bar(entry: dict, mode: str, key: str, share: float) -> dict:
    value, direct = entry[mode].get(key), entry["direct"].get(key)
    limit = None if direct is None else share * direct
    seeds = entry[mode]["seeds"]
    return _bar(value, limit, _at_most(value, limit) and seeds >= MIN_SEEDS, **_seeds(seeds))


def _bar_profile_bars(report: dict, mode: str, shares: Bars) -> dict:
    bars = {}
    if "tracking" in report:
        bars["tracking"] = _ratio_bar(report["tracking"], mode, "joint_rmse", shares.tracking)
    if "circle" in report:
        bars["circle"] = _ratio_bar(report["circle"], mode, "mean_deviation_from_simulator", shares.circle)
    barred = [e for e in EXPERIMENTS_BARRED if e in report]
    if barred:
        new = sum(_new_falls(report[e], mode) for e in barred)
        seeds = min(report[e][mode]["seeds"] for e in barred)
        bars["no_new_falls"] = _bar(new, 0, new == 0 and seeds >= MIN_SEEDS, **_seeds(seeds))
    return bars


def _no_worse_bar(report: dict, mode: str) -> dict | None:
    """The experiment where `mode` does worst against direct: its RMSE against direct's, and no new falls."""
    worst = None
    for name in (e for e in report if e != "sweeps" and isinstance(report[e], dict) and mode in report[e]):
        value, direct = report[name][mode]["joint_rmse"], report[name]["direct"]["joint_rmse"]
        ratio = math.inf if value is None or not math.isfinite(value) else (
            value / direct if direct else (0.0 if value == 0.0 else math.inf))
        if worst is None or ratio > worst[0]:
            worst = (ratio, name, value, direct)
    if worst is None:
        return None
    falls = sum(max(0, report[e][mode]["falls"] - report[e]["direct"]["falls"])
                for e in report if e != "sweeps" and isinstance(report[e], dict) and mode in report[e])
    _, name, value, direct = worst
    return _bar(value, direct, _at_most(value, direct) and falls == 0, experiment=name, new_falls=falls)


def acceptance(profiles: dict[str, dict], modes, estimator: str = "kinematic") -> dict:
    """Per mode other than direct, every bar the reports have data for (docs/transfer.md), with the shares of
    `BARS[estimator]`. `profiles` maps a profile name to its report (experiments -> mode -> metrics over seeds;
    "sweeps" where the sweeps ran)."""
    shares = BARS[estimator]
    bar_profile = BAR_PROFILE if BAR_PROFILE in profiles else next(iter(profiles), None)
    sweep_rows = next((p["sweeps"]["latency"] for p in profiles.values() if p.get("sweeps", {}).get("latency")), [])
    table: dict = {}
    for mode in (m for m in modes if m != "direct"):
        bars = _bar_profile_bars(profiles[bar_profile], mode, shares) if bar_profile is not None else {}
        for bar in bars.values():
            bar["profile"] = bar_profile
        if NULL_PROFILE in profiles:
            report = profiles[NULL_PROFILE]
            values = [report[e][mode]["joint_rmse"] for e in report if e != "sweeps" and mode in report[e]]
            if values:
                worst = max(values, key=lambda v: math.inf if v is None or not math.isfinite(v) else v)
                bars["none"] = _bar(worst, NULL_RMSE, _at_most(worst, NULL_RMSE), profile=NULL_PROFILE)
        for name in (p for p in ONE_FACTOR_PROFILES if p in profiles):
            bar = _no_worse_bar(profiles[name], mode)
            if bar is not None:
                bars[f"one_factor:{name}"] = bar
        if sweep_rows and mode in sweep_rows[0]:
            value, limit = latency_tolerance(sweep_rows, mode), latency_tolerance(sweep_rows, "direct")
            passed = (-math.inf if value is None else value) >= (-math.inf if limit is None else limit)
            bars["latency"] = _bar(value, limit, passed, unit="ms")
        table[mode] = bars
    return table


def recommended(table: dict) -> str | None:
    """Of the candidate modes in an `acceptance` table, the one that passes every bar it has (tracking and circle
    among them) with the lowest tracking RMSE; None when none does."""
    passing = [(bars["tracking"]["value"], mode) for mode, bars in table.items()
               if is_candidate(mode) and "tracking" in bars and "circle" in bars
               and all(bar["pass"] for bar in bars.values())]
    return min(passing)[1] if passing else None
