"""`bruce-eval replay`'s figure and tables: Fig. 6 for a recorded run (`plot`) and the Markdown table (`markdown`),
from the analysis of `training.evaluation.replay`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from training.evaluation.replay import RunLog, aligned, forward_velocity, window_of


def plot(path: Path, robot: RunLog, simulation: RunLog, predicted: dict[str, np.ndarray], report: dict,
         joint: int, window: tuple[float, float] | None) -> None:
    """Fig. 6 for a recorded run: joint `joint`'s angle, velocity and torque and its phase portrait, robot against
    the simulation (and the one-step predictions), the per-joint RMSE, the one-step velocity residual."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    name = robot.joints[joint]
    a, b = aligned(robot, simulation)
    shown = window_of(a.t, window)
    fig, axes = plt.subplots(2, 4, figsize=(20, 8))
    runs = (("robot (log)", "k", a), ("simulator (closed loop)", "tab:blue", b))
    colours = {"pinn": "tab:red", "nominal": "tab:green"}
    one_step_rows = window_of(robot.t, window)
    for label, colour, run in runs:
        kw = {"color": colour, "label": label, "lw": 0.9}
        axes[0, 0].plot(run.t[shown], run.q[shown, joint], **kw)
        axes[0, 1].plot(run.t[shown], run.qd[shown, joint], **kw)
        axes[0, 2].plot(run.t[shown], run.tau[shown, joint], **kw)
        axes[0, 3].plot(run.q[shown, joint], run.qd[shown, joint], **kw)
    for model, values in predicted.items():
        kw = {"color": colours[model], "lw": 0.7, "ls": "--", "label": f"{model}, one step along the log"}
        axes[0, 0].plot(robot.t[one_step_rows], values[one_step_rows, 0, joint], **kw)
        axes[0, 1].plot(robot.t[one_step_rows], values[one_step_rows, 1, joint], **kw)
    titles = (f"{name} angle (rad)", f"{name} velocity (rad/s)", f"{name} torque written (N m)",
              f"{name} phase portrait (rad, rad/s)")
    for ax, title in zip(axes[0], titles, strict=True):
        ax.set_title(title)
        ax.legend(fontsize=7)
    x = np.arange(len(robot.joints))
    closed = report["closed_loop"]
    axes[1, 0].bar(x, list(closed["joint_rmse_per_joint"].values()), color="tab:blue")
    axes[1, 0].set_title(f"joint RMSE, robot vs simulator (rad); mean {closed['joint_rmse']:.4g}")
    bars = {model: report["one_step"][model] for model in predicted if report["one_step"][model].get("transitions")}
    gap = report.get("gap_monitor")
    if gap and gap.get("samples"):
        bars["live gap monitor"] = {"rmse_qd_per_joint": gap["rms_qd_per_joint"]}
    width = 0.8 / max(len(bars), 1)
    for i, (label, entry) in enumerate(bars.items()):
        axes[1, 1].bar(x + (i - (len(bars) - 1) / 2) * width, list(entry["rmse_qd_per_joint"].values()), width,
                       color=colours.get(label, "tab:purple"), label=label)
    axes[1, 1].set_title("one-step velocity RMSE along the log (rad/s)")
    axes[1, 1].legend(fontsize=7)
    for ax in axes[1, :2]:
        ax.set_xticks(x, robot.joints, rotation=60, fontsize=7)
    for model, values in predicted.items():
        axes[1, 2].plot(robot.t[one_step_rows], robot.column("qd")[one_step_rows, joint]
                        - values[one_step_rows, 1, joint], color=colours[model], lw=0.7, label=model)
    if robot.has("gap_qd"):
        axes[1, 2].plot(robot.t[one_step_rows], robot.column("gap_qd")[one_step_rows, joint], color="tab:purple",
                        lw=0.7, label=f"live gap monitor ({robot.meta.get('reference_model')})")
    axes[1, 2].set_title(f"{name} one-step velocity residual, measured - predicted (rad/s)")
    axes[1, 2].legend(fontsize=7)
    speed_robot, speed_sim = forward_velocity(robot), forward_velocity(simulation)
    if speed_robot is not None and speed_sim is not None:
        axes[1, 3].plot(robot.t[::10], speed_robot, color="k", lw=0.9, label="robot (log, simulator truth)")
        axes[1, 3].plot(simulation.t[::10], speed_sim, color="tab:blue", lw=0.9, label="simulator (closed loop)")
        axes[1, 3].set_title("forward velocity (m/s)")
    else:
        axes[1, 3].set_title("velocity command vx (m/s) (no base velocity in a robot's log)")
    axes[1, 3].plot(robot.t, robot.column("command")[:, 0], color="0.5", lw=0.8, ls=":", label="command vx")
    axes[1, 3].legend(fontsize=7)
    fig.suptitle(f"{robot.path}: robot log against the nominal simulator and the PINN")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _fmt(value) -> str:
    return "—" if value is None else f"{value:.4g}"


def _ended(ended: dict | None) -> str:
    ended = ended or {}
    cause = ended.get("error") or ended.get("stop_cause") or ended.get("note") or "not recorded (no close)"
    return cause + (f" (exit code {ended['exit_code']})" if ended.get("exit_code") is not None else "")


def markdown(report: dict) -> str:
    meta, closed, one_step, gap = report["meta"], report["closed_loop"], report["one_step"], report["gap_monitor"]
    log = meta["log"]
    lines = [f"# Replay of {meta['log_path']}", "",
             f"{log['backend']} backend, {log['controller']}, transfer {log['transfer']}, "
             f"gap {log['gap']['profile'] if log['gap'] else 'none (no profile)'}; {closed['ticks']} ticks compared "
             f"({log['rows_written']} rows, {log['rows_dropped']} dropped); the run ended: {_ended(log['ended'])}",
             "",
             "| joint | RMSE q vs simulator (rad) | offset (rad) | RMSE qd vs simulator (rad/s) | "
             "one-step qd RMSE PINN (rad/s) | one-step qd RMSE nominal (rad/s) | live gap monitor qd RMS (rad/s) |",
             "|---|---|---|---|---|---|---|"]
    for name in closed["joint_rmse_per_joint"]:
        cells = [closed["joint_rmse_per_joint"][name], closed["offset_per_joint"][name],
                 closed["joint_velocity_rmse_per_joint"][name],
                 one_step["pinn"].get("rmse_qd_per_joint", {}).get(name),
                 one_step["nominal"].get("rmse_qd_per_joint", {}).get(name),
                 (gap or {}).get("rms_qd_per_joint", {}).get(name)]
        lines.append(f"| {name} | " + " | ".join(_fmt(c) for c in cells) + " |")
    lines.append(f"| **mean** | **{_fmt(closed['joint_rmse'])}** | | **{_fmt(closed['joint_velocity_rmse'])}** | "
                 f"{_fmt(one_step['pinn'].get('rmse_qd'))} | {_fmt(one_step['nominal'].get('rmse_qd'))} | "
                 f"{_fmt((gap or {}).get('rms_qd'))} |")
    notes = [f"- {key}: {value}" for key, value in one_step.items() if "unavailable" in value]
    notes += [f"- {note}" for note in meta["notes"]]
    return "\n".join(lines + ([""] + notes if notes else [])) + "\n"
