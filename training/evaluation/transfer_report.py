"""The transfer rehearsal's outputs: transfer.md (`markdown` per profile, `suite_markdown` over a suite) and the
figures (`plot`: Figs. 6-10)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from runtime.loop.observers import TRACKING_SKIP_S
from training.evaluation.transfer_acceptance import BARS, recommended
from training.evaluation.transfer_metrics import ideal_path
from training.evaluation.transfer_runs import LOOKAHEAD_MODE, MODE_NAMES, mode_label


def _fmt(value, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "—"
    return f"{value:.{digits}g}"


def markdown(report: dict, meta: dict) -> str:
    experiments = [entry for name, entry in report.items() if name != "sweeps"]
    modes = list(meta.get("modes") or [m for m in ("direct", "pinn", LOOKAHEAD_MODE)
                                        if experiments and m in experiments[0]])
    names = {m: mode_label(m) for m in modes}
    ahead = f"; look-ahead: {meta['lookahead']} ticks" if LOOKAHEAD_MODE in modes else ""
    lines = [f"# Transfer rehearsal: gap profile `{meta['gap_name']}`", "",
             f"Controller `{meta['controller']}`, estimator `{meta['estimator']}`, {meta['seconds']:g} s per run, "
             f"gap seeds {meta['seeds']} (mean over seeds; falls = seeds that fell){ahead}. Scored after "
             f"{TRACKING_SKIP_S:g} s on simulator truth against the nominal mock (Eq. 8, no gap); a run that fell "
             "is scored up to its fall.", "",
             "| experiment | metric | nominal | " + " | ".join(names[m] for m in modes) + " | "
             + " | ".join(f"{names[m]} / direct" for m in modes[1:]) + " |",
             "|---|---|---|" + "---|" * (2 * len(modes) - 1)]
    rows = (("tracking", "joint_rmse", "joint RMSE (rad)"),
            ("tracking", "joint_velocity_rmse", "joint velocity RMSE (rad/s)"),
            ("circle", "mean_radial_deviation", "mean radial deviation (m)"),
            ("circle", "mean_deviation_from_simulator", "deviation from the simulator's path (m)"),
            ("reverse", "drift", "drift (m)"), ("turn", "drift", "drift (m)"))
    for name, key, label in rows:
        if name not in report:
            continue
        entry = report[name]
        direct = entry["direct"].get(key)
        values = [_fmt(entry[m].get(key)) for m in modes]
        ratios = [_fmt(entry[m].get(key, float("nan")) / direct if direct else None) for m in modes[1:]]
        lines.append(f"| {name} | {label} | {_fmt(entry['nominal'].get(key))} | " + " | ".join(values) + " | "
                     + " | ".join(ratios) + " |")
    for name in ("tracking", "circle", "reverse", "turn"):
        if name in report:
            entry = report[name]
            lines.append(f"| {name} | falls | {int(entry['nominal']['fell'])}/1 | "
                         + " | ".join(f"{entry[m]['falls']}/{entry[m]['seeds']}" for m in modes)
                         + " |" * len(modes))
    sweeps = report.get("sweeps", {})
    if sweeps.get("latency"):
        swept = [m for m in modes if m in sweeps["latency"][0]]
        lines += ["", "Tracking joint RMSE (rad) against actuator latency (falls in brackets):", "",
                  "| latency (ms) | " + " | ".join(names[m] for m in swept) + " |", "|---|" + "---|" * len(swept)]
        for row in sweeps["latency"]:
            cells = [f"{_fmt(row[m]['joint_rmse'])}" + (f" ({row[m]['falls']}/{row[m]['seeds']} fell)"
                                                         if row[m]["falls"] else "") for m in swept]
            lines.append(f"| {row['latency_ms']:g} | " + " | ".join(cells) + " |")
    if sweeps.get("eq9_gain"):
        lines += ["", f"Tracking joint RMSE (rad) against the Eq. 9 gains (scale on Kp', Kd'); direct transfer: "
                      f"{_fmt(sweeps.get('eq9_gain_direct_reference'))}:", "", "| scale | PINN (Eq. 9) |",
                  "|---|---|"]
        for row in sweeps["eq9_gain"]:
            fell = f" ({row['pinn']['falls']}/{row['pinn']['seeds']} fell)" if row["pinn"]["falls"] else ""
            lines.append(f"| {row['scale']:g} | {_fmt(row['pinn']['joint_rmse'])}{fell} |")
    return "\n".join(lines) + "\n"


def _mean_std(entry: dict, key: str) -> str:
    value, std = entry.get(key), entry.get(f"{key}_std")
    return _fmt(value) + (f" ± {_fmt(std, 2)}" if std is not None and value is not None else "")


def suite_markdown(reports: dict[str, dict], modes, table: dict, estimator: str = "kinematic") -> str:
    """Every profile x mode x experiment (mean ± std over seeds, falls), the latency each mode tolerates, and the
    acceptance bars of each mode with the recommendation."""
    names = {m: "Eq. 9 (paper)" if m in ("pinn", "eq9") else mode_label(m) for m in modes}
    lines = ["## Every profile", "",
             "Joint RMSE (rad) against the nominal run, offset / shape its split (RMS over joints of each joint's "
             "mean error / of the rest); circle: distance from the simulator's own base path at the same tick and "
             "from the ideal circle (m); falls over seeds.", "",
             "| profile | scheme | tracking RMSE | offset / shape | circle RMSE | circle dev. vs simulator | "
             "circle dev. (ideal) | falls |", "|---|---|---|---|---|---|---|---|"]
    for profile, report in reports.items():
        tracking, circle = report.get("tracking", {}), report.get("circle", {})
        for mode in modes:
            t, c = tracking.get(mode, {}), circle.get(mode, {})
            falls = " · ".join(f"{name} {report[name][mode]['falls']}/{report[name][mode]['seeds']}"
                               for name in report if name != "sweeps" and mode in report[name])
            lines.append(f"| {profile} | {names[mode]} | {_mean_std(t, 'joint_rmse')} | {_fmt(t.get('offset'))} / "
                         f"{_fmt(t.get('shape'))} | {_mean_std(c, 'joint_rmse')} | "
                         f"{_mean_std(c, 'mean_deviation_from_simulator')} | {_mean_std(c, 'mean_radial_deviation')} "
                         f"| {falls} |")
    tolerance = next((r["sweeps"]["latency_tolerance_ms"] for r in reports.values()
                      if "latency_tolerance_ms" in r.get("sweeps", {})), None)
    if tolerance:
        lines += ["", f"Actuator latency tolerated (ms; the largest swept latency up to which no seed fell), on "
                      f"`{next(iter(reports))}`:", "", "| " + " | ".join(names[m] for m in modes) + " |",
                  "|" + "---|" * len(modes), "| " + " | ".join(_fmt(tolerance.get(m)) for m in modes) + " |"]
    lines += ["", f"## Acceptance ({estimator}: issue {BARS[estimator].issue}'s bars)", "",
              "| scheme | bar | value | limit | pass |", "|---|---|---|---|---|"]
    for mode, bars in table.items():
        for bar, result in bars.items():
            where = f" ({result['experiment']})" if "experiment" in result else ""
            note = f" ({result['note']})" if "note" in result else ""
            lines.append(f"| {names.get(mode, mode)} | {bar}{where} | {_fmt(result['value'])} | "
                         f"{_fmt(result['limit'])} | {'yes' if result['pass'] else 'no'}{note} |")
    choice = recommended(table)
    lines += ["", f"Recommended: **{names[choice]}**" if choice else
              "Recommended: none (no scheme other than Eq. 9 and the perfect-model controls passes every bar)."]
    return "\n".join(lines) + "\n"


def plot(out: Path, report: dict, traces: dict, joint_names: tuple[str, ...]) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    modes = [m for m in (traces.get("tracking") or next(iter(traces.values()), {})) if m != "nominal"]
    cycle = ("tab:red", "tab:blue", "tab:green", "tab:orange", "tab:purple", "tab:brown", "tab:pink", "tab:olive")
    colours = {"nominal": "k", "direct": "tab:red", "pinn": "tab:blue", LOOKAHEAD_MODE: "tab:green"}
    for mode in modes:
        colours.setdefault(mode, cycle[len(colours) % len(cycle)])
    labels = {"nominal": "simulator (nominal)", **{m: mode_label(m) for m in modes}}
    written = []
    if "tracking" in traces:
        fig, axes = plt.subplots(2, 3, figsize=(15, 7.5))
        for mode, record in traces["tracking"].items():
            kw = {"color": colours[mode], "label": labels[mode], "lw": 0.8}
            window = (record.t >= 10.0) & (record.t < 11.0)
            axes[0, 0].plot(record.t[window], record.q[window, 0], **kw)
            axes[0, 1].plot(record.t[window], record.qd[window, 0], **kw)
            axes[0, 2].plot(record.t[window], record.tau[window, 0], **kw)
            axes[1, 0].plot(record.q[window, 0], record.qd[window, 0], **kw)
            axes[1, 1].plot(record.t[::10], record.velocity[::10, 0], **kw)
        for ax, title in zip(axes.flat, (f"{joint_names[0]} angle (rad)", f"{joint_names[0]} velocity (rad/s)",
                                         f"{joint_names[0]} torque (N m)", f"{joint_names[0]} phase portrait",
                                         "forward velocity (m/s)"), strict=False):
            ax.set_title(title)
            ax.legend(fontsize=7)
        entry = report["tracking"]
        x = np.arange(len(joint_names))
        shown = [m for m in modes if m in entry]
        width = 0.8 / len(shown)
        for i, mode in enumerate(shown):
            axes[1, 2].bar(x + (i - (len(shown) - 1) / 2) * width, entry[mode]["joint_rmse_per_joint"], width,
                           color=colours[mode], label=labels[mode])
        axes[1, 2].set_xticks(x, joint_names, rotation=60, fontsize=7)
        axes[1, 2].set_title("joint RMSE against the simulator (rad)")
        axes[1, 2].legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / "fig6_tracking.png", dpi=110)
        plt.close(fig)
        written.append("fig6_tracking.png")
    for name, figure in (("circle", "fig7_circle.png"), ("reverse", "fig8_reverse.png"), ("turn", "fig9_turn.png")):
        if name not in traces:
            continue
        fig, (path_ax, speed_ax) = plt.subplots(1, 2, figsize=(12, 5))
        command = tuple(report[name]["command"])
        for mode, record in traces[name].items():
            kw = {"color": colours[mode], "label": labels[mode], "lw": 1.0}
            path_ax.plot(record.xy[:, 0], record.xy[:, 1], **kw)
            axis = 2 if command[0] == 0.0 else 0
            speed_ax.plot(record.t[::10], record.velocity[::10, axis], **kw)
        nominal = traces[name]["nominal"]
        if name == "circle":
            circle = report[name]["nominal"]
            theta = np.linspace(0, 2 * np.pi, 200)
            path_ax.plot(circle["centre"][0] + circle["radius"] * np.cos(theta),
                         circle["centre"][1] + circle["radius"] * np.sin(theta), "k--", lw=0.8, label="ideal circle")
        elif len(nominal.t):
            ideal = ideal_path(command, nominal.t, nominal.xy[0], float(nominal.yaw[0]))
            path_ax.plot(ideal[:, 0], ideal[:, 1], "k--", lw=0.8, label="commanded path")
        path_ax.set_aspect("equal", adjustable="datalim")
        path_ax.set_title(f"{name}: base path (m), command {command}")
        speed_ax.set_title("yaw rate (rad/s)" if command[0] == 0.0 else "forward velocity (m/s)")
        path_ax.legend(fontsize=7)
        speed_ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / figure, dpi=110)
        plt.close(fig)
        written.append(figure)
    sweeps = report.get("sweeps", {})
    if sweeps.get("latency") or sweeps.get("eq9_gain"):
        fig, (lat_ax, gain_ax) = plt.subplots(1, 2, figsize=(12, 4.5))
        if sweeps.get("latency"):
            lat = [r["latency_ms"] for r in sweeps["latency"]]
            for mode in (m for m in colours if m in sweeps["latency"][0]):
                lat_ax.plot(lat, [r[mode]["joint_rmse"] for r in sweeps["latency"]], "o-", color=colours[mode],
                            label=labels[mode])
            lat_ax.set_xlabel("actuator latency (ms)")
            lat_ax.set_ylabel("tracking joint RMSE (rad)")
            lat_ax.legend(fontsize=8)
        if sweeps.get("eq9_gain"):
            scale = [r["scale"] for r in sweeps["eq9_gain"]]
            gain_ax.plot(scale, [r["pinn"]["joint_rmse"] for r in sweeps["eq9_gain"]], "o-", color=colours["pinn"],
                         label=MODE_NAMES["pinn"])
            if sweeps.get("eq9_gain_direct_reference") is not None:
                gain_ax.axhline(sweeps["eq9_gain_direct_reference"], color=colours["direct"], ls="--",
                                label=labels["direct"])
            gain_ax.set_xlabel("Eq. 9 gain scale (Kp', Kd')")
            gain_ax.set_ylabel("tracking joint RMSE (rad)")
            gain_ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(out / "fig10_sweeps.png", dpi=110)
        plt.close(fig)
        written.append("fig10_sweeps.png")
    return written
