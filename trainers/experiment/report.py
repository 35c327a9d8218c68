"""The experiment's outputs: table.md and table.json from the cached evaluations and the runs'
files, and the curves (:mod:`.curves`); what is kept of them is :mod:`.evidence`'s."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from overtake.client.episodes.records import RecordError, read_header
from overtake.protocol.vocabulary import WATCH_METRICS

from ..run.checkpoint import plain_data
from ..run.run_files import git_commit, package_versions
from .catalogue import (
    ALGO_NAMES,
    EXPERIMENTS,
    INPUT_NAMES,
    TABLE_COLUMNS,
    Density,
    Row,
)
from .curves import plot_curves, record_curves
from .evidence import portable, provenance_line, run_lives
from .files import (
    checkpoint_step,
    training_episodes,
    training_records,
    utc_now,
    window_rewards,
    write_atomic,
)
from .plan import ExperimentConfig, Plan
from .run import ExperimentRun
from .statistics import episode_statistics, learning_curves, seed_order, seed_statistics


def _cell(stats: dict[str, Any], metric: str, decimals: int) -> str:
    return f"{stats[metric]['mean']:.{decimals}f} ± {stats[metric]['std']:.{decimals}f}"


def _safety_cell(stats: dict[str, Any], name: str) -> str:
    """A safety count per episode (mean ± spread) and per km driven; ``-`` where it did not
    run."""
    if name not in stats:
        return "-"
    per_km = stats.get(f"{name}_per_km")
    return _cell(stats, name, 1) + (f" ({per_km['mean']:.2f})" if per_km else "")


def markdown_table(result: dict[str, Any]) -> str:
    """table.md: one table per density, the rows then the reference policies."""
    plan = result["plan"]
    episodes, seed = plan["eval_episodes"], plan["eval_seed"]
    runs = [run for row in next(iter(result["densities"].values()))["rows"] for run in row["runs"]]
    runs_made = bool(runs) and any("provenance" in run for run in runs)  # the section below
    lines = [
        f"# {result['experiment']}: {plan['title']}",
        "",
        f"Training: {plan['total_steps']:,} environment steps per run, preset "
        f"{plan['preset']}, {plan['num_envs']} environments, "
        f"{plan['train_traffic'] or 'the preset’s'} traffic; learning starts at "
        f"{plan['schedule']['learning_starts']:,} steps, epsilon 1 → 0.1 over "
        f"{plan['schedule']['epsilon_decay_steps']:,}, target copy every "
        f"{plan['schedule']['target_update_steps']:,}, replay "
        f"{plan['schedule']['replay_size']:,}.",
        f"Evaluation: greedy, {episodes} episodes per policy and density on seeds "
        f"{seed}–{seed + episodes - 1} (the same for every policy). Mean ± spread (standard "
        "deviation) over the episodes; a row with several training seeds pools the episodes "
        "of all of them (per-seed means below its table). Collisions per 1,000 decisions: "
        "each episode's own rate.",
        f"Tabulated by code {result['commit']}, written {result['written_utc']}; evaluated by "
        f"code {', '.join(evaluation_commits(result))}"
        + ("; each run's training code is under “How each run was made”." if runs_made else "."),
    ]
    headings = [heading for _, heading, _ in TABLE_COLUMNS]
    for density, table in result["densities"].items():
        # Safety's columns: the shield's overrides, and the lane changes turned back where
        # any row's driver assistance watched them (per episode, and per km driven).
        safety = [("shield_overrides", "shield overrides")]
        if any(WATCH_METRICS[0] in row["summary"] for row in table["rows"]):
            safety.append((WATCH_METRICS[0], "lane changes turned back"))
        lines += [
            "",
            f"## {density.capitalize()} traffic",
            "",
            "| policy | algorithm | inputs | training seeds | " + " | ".join(headings) + " | "
            "options | " + " | ".join(f"{h} (per km)" for _, h in safety) + " |",
            "|---|---|---|---:|" + "---:|" * len(headings) + "---|" + "---:|" * len(safety),
        ]
        for row in table["rows"]:
            cells = [_cell(row["summary"], m, d) for m, _, d in TABLE_COLUMNS]
            lines.append(
                f"| {row['label']} | {ALGO_NAMES[row['algo']]} | {INPUT_NAMES[row['inputs']]} "
                f"| {len(row['runs'])} | "
                + " | ".join(cells)
                + f" | {row.get('options', '-')} | "
                + " | ".join(_safety_cell(row["summary"], name) for name, _ in safety)
                + " |"
            )
        for reference in table["references"]:
            cells = [_cell(reference["summary"], m, d) for m, _, d in TABLE_COLUMNS]
            lines.append(
                f"| {reference['policy']} | reference policy | - | - | "
                + " | ".join(cells)
                + " | - | "
                + " | ".join(_safety_cell(reference["summary"], name) for name, _ in safety)
                + " |"
            )
        crashed = [
            line
            for row in table["rows"]
            for run in row["runs"]
            for line in _collision_lines(run["run"], run)
        ] + [
            line
            for reference in table["references"]
            for line in _collision_lines(reference["policy"], reference)
        ]
        lines += (
            ["", *_folded(COLLISIONS_SUMMARY, [REPLAY_PATHS, "", *crashed])]
            if crashed
            else ["", "Episodes with collisions: none."]
        )
        several = [row for row in table["rows"] if len(row["runs"]) > 1]
        if several:
            lines += [
                "",
                "Per training seed (means over each seed's episodes; spread over the seeds "
                "in the last line of each row):",
                "",
                "| run | " + " | ".join(headings) + " |",
                "|---|" + "---:|" * len(headings),
            ]
            for row in several:
                for run in row["runs"]:
                    cells = [f"{run['summary'][m]['mean']:.{d}f}" for m, _, d in TABLE_COLUMNS]
                    lines.append(f"| {run['run']} | " + " | ".join(cells) + " |")
                cells = [f"± {row['seeds'][m]['std']:.{d}f}" for m, _, d in TABLE_COLUMNS]
                lines.append(f"| {row['label']}: spread over seeds | " + " | ".join(cells) + " |")
            if len(several) > 1:
                lines += [
                    "",
                    "The order of these rows by average speed, against the seed spread (it "
                    "holds beyond the spread when every seed of the faster row is faster than "
                    "every seed of the slower):",
                    "",
                ]
                means = {row["label"]: row["seeds"]["avg_speed_kmh"]["means"] for row in several}
                for pair in table["order"]:
                    high, low = means[pair["higher"]], means[pair["lower"]]
                    verdict = (
                        "beyond the seed spread"
                        if pair["beyond_seed_spread"]
                        else "in the means only (the seeds overlap)"
                    )
                    lines.append(
                        f"- {pair['higher']} ({min(high):.1f}–{max(high):.1f}) > "
                        f"{pair['lower']} ({min(low):.1f}–{max(low):.1f}) by "
                        f"{pair['difference']:.1f} km/h: {verdict}"
                    )
    if runs_made:
        lines += ["", "## How each run was made", ""]
        lines += [f"- {run['run']}: {provenance_line(run.get('provenance', []))}" for run in runs]
    experiment = EXPERIMENTS.get(result["experiment"])
    if experiment is not None and experiment.note:
        lines += ["", "## Reading it", "", experiment.note]
    if experiment is not None and experiment.paper:
        lines += ["", "## The paper's figures", "", experiment.paper]
    return "\n".join(lines) + "\n"


def _relative(path: Path | None, root: Path) -> Path | None:
    """``path`` within ``root`` (an evaluation's cache file, named in table.json)."""
    if path is None:
        return None
    try:
        return path.relative_to(root)
    except ValueError:
        return path


def _versions() -> dict[str, str]:
    versions = package_versions()
    from importlib import metadata

    for name in ("matplotlib", "rerun-sdk", "tyro"):
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return versions


def _from_record(result: dict[str, Any], out: Path) -> dict[str, Any]:
    """What a table takes from an evaluation's episode record: the episodes with a collision
    (their numbers: episode i had seed eval_seed + i), the record's path within the
    experiment's directory ``out`` (so that the kept copy names it too: overtake-replay plays
    them from it), and the commit of the code that drove them (its header's)."""
    record = result.get("episodes_record")
    return {
        "collision_episodes": [
            i for i, episode in enumerate(result["episodes"]) if episode["collisions"] > 0
        ],
        "episodes_record": str(_relative(Path(record), out)) if record else None,
        "evaluated_by": _record_commit(Path(record)) if record else None,
    }


def _record_commit(record: Path) -> str | None:
    """The commit in a record's header; None where the record is gone or is not one."""
    try:
        return read_header(record).commit or None
    except RecordError:
        return None


def evaluation_commits(result: dict[str, Any]) -> list[str]:
    """The commits whose code evaluated a table's rows and references (table.json's
    ``evaluated_by``), in order of first appearance; "unknown" for evaluations without one."""
    found: dict[str, None] = {}
    for table in result["densities"].values():
        entries = [run for row in table["rows"] for run in row["runs"]]
        for entry in [*entries, *table["references"]]:
            found[entry.get("evaluated_by") or "unknown"] = None
    return list(found)


COLLISIONS_SUMMARY = "Episodes with collisions, and the command that replays them in Rerun"
REPLAY_PATHS = (
    "Run these in the experiment's directory. Its copy kept in bench/results/ holds the "
    "collision episodes of each record but not the checkpoints: add `--actions-only` there "
    "(the episodes play as recorded, without the network's Q-values)."
)


def _folded(summary: str, lines: list[str]) -> list[str]:
    """``lines`` in a collapsed block that GitHub and the documentation site (md_in_html)
    both render as Markdown: long lists stay out of the reader's way."""
    return [f'<details markdown="1"><summary>{summary}</summary>', "", *lines, "", "</details>"]


def _collision_lines(name: str, entry: dict[str, Any]) -> list[str]:
    episodes = entry.get("collision_episodes")
    if not episodes:
        return [] if episodes is not None else [f"- {name}: not counted (an older evaluation)"]
    record = entry.get("episodes_record")
    replay = (
        f"`overtake-replay {record} --collisions --rrd {Path(record).stem}-collisions.rrd`"
        if record
        else "no episode record (evaluated before records were kept)"
    )
    return [f"- {name}: episodes {', '.join(map(str, episodes))}: {replay}"]


class Outputs:
    """The table and the curves, from the cached evaluations and the runs' metrics."""

    def __init__(self, config: ExperimentConfig, plan: Plan, experiment_run: ExperimentRun):
        self.config, self.plan, self.run = config, plan, experiment_run

    def result(self) -> dict[str, Any]:
        plan = self.plan
        densities: dict[str, Any] = {}
        for density in plan.densities:
            rows = [self._row(row, density) for row in plan.rows]
            densities[density] = {
                "rows": rows,
                "order": seed_order(rows),
                "references": [self._reference(policy, density) for policy in plan.references],
            }
        curves = {}
        for row in plan.rows:
            runs = [run for run in plan.runs if run.row == row]
            curve = learning_curves(
                {run.name: training_episodes(run.run_dir) for run in runs},
                plan.total_steps,
                self.config.curve_bins,
            )
            window = plan.experiment.reward_window_steps
            if window:
                curve["window_reward"] = window_rewards(
                    {run.name: training_records(run.run_dir, "train") for run in runs}, window
                )
            curves[row.label] = {"runs": len(runs), **curve}
        window = plan.experiment.reward_window_steps
        never_acting = self._never_acting(window) if window else None
        if never_acting is not None:
            for curve in curves.values():
                curve["window_reference"] = {"never acting (idle)": never_acting}
        experiment = plan.experiment
        return {
            "experiment": experiment.name,
            "plan": {
                "title": experiment.title,
                "rows": [dataclasses.asdict(row) for row in plan.rows],
                "preset": experiment.preset,
                "total_steps": plan.total_steps,
                "num_envs": plan.runs[0].train.num_envs if plan.runs else None,
                "train_traffic": experiment.train_traffic,
                "schedule": dataclasses.asdict(plan.schedule),
                "densities": list(plan.densities),
                "references": list(plan.references),
                "eval_episodes": plan.eval_episodes,
                "eval_seed": self.config.eval_seed,
                "eval_max_decisions": self.config.eval_max_decisions,
                "runs": {run.name: plain_data(run.train) for run in plan.runs},
            },
            "config": plain_data(self.config),
            "versions": _versions(),
            "commit": git_commit(),
            "written_utc": utc_now(),
            "densities": densities,
            "curves": curves,
        }

    def _row(self, row: Row, density: Density) -> dict[str, Any]:
        runs: list[dict[str, Any]] = []
        pooled: list[dict[str, float]] = []
        for run in (run for run in self.plan.runs if run.row == row):
            step = checkpoint_step(run.run_dir)
            assert step is not None  # every run finished before the outputs are written
            [task] = [
                t for t in self.run.eval_tasks_of_run(run, step) if t.key["density"] == density
            ]
            result = self.run.cached(task)
            assert result is not None
            runs.append(
                {
                    "run": run.name,
                    "seed": run.seed,
                    "checkpoint_step": step,
                    "summary": episode_statistics(result["episodes"]),
                    "evaluation": str(_relative(task.cache, self.plan.out)),
                    "decisions_per_s": result["decisions_per_s"],
                    **_from_record(result, self.plan.out),
                    "provenance": run_lives(run.run_dir, step),
                }
            )
            pooled.extend(result["episodes"])
        return {
            "label": row.label,
            "algo": row.algo,
            "inputs": row.inputs,
            "options": row.options,
            "summary": episode_statistics(pooled),
            "seeds": seed_statistics([run["summary"] for run in runs]),
            "runs": runs,
        }

    def _never_acting(self, window: int) -> float | None:
        """What a driver that never acts (the idle reference) earns per ``window`` steps in
        the traffic the runs trained in: its evaluation's reward per decision, pooled over
        its episodes, times the window (a learning curve's reference line: Fayjie et al.'s
        reward pays for keeping going). None where idle was not evaluated there."""
        # Every preset trains in medium traffic unless the experiment names another.
        density = self.plan.experiment.train_traffic or "medium"
        tasks = [
            t
            for t in self.run.reference_tasks()
            if t.key["policy"] == "idle" and t.key["density"] == density
        ]
        result = self.run.cached(tasks[0]) if tasks else None
        if result is None:
            return None
        decisions = sum(episode["decisions"] for episode in result["episodes"])
        reward = sum(episode["return"] for episode in result["episodes"])
        return reward / decisions * window if decisions else None

    def _reference(self, policy: str, density: Density) -> dict[str, Any]:
        [task] = [
            t
            for t in self.run.reference_tasks()
            if t.key["policy"] == policy and t.key["density"] == density
        ]
        result = self.run.cached(task)
        assert result is not None
        return {
            "policy": policy,
            "summary": episode_statistics(result["episodes"]),
            "evaluation": str(_relative(task.cache, self.plan.out)),
            "decisions_per_s": result["decisions_per_s"],
            **_from_record(result, self.plan.out),
        }

    def write(self) -> dict[str, Any]:
        out = self.plan.out
        result = portable(self.result(), out)
        write_atomic(out / "table.json", json.dumps(result, indent=1))
        write_atomic(out / "table.md", markdown_table(result))
        title = f"{self.plan.experiment.name}: training episodes ({self.config.curve_bins} bins)"
        plot_curves(result["curves"], title, out / "curves.png")
        record_curves(result["curves"], self.plan.experiment.name, out / "curves.rrd")
        return result
