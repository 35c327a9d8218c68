"""``overtake-experiment``: a paper's table reproduced by one resumable command.

An experiment is data (:data:`EXPERIMENTS`): the table's rows (an algorithm on some inputs,
trained from one or more seeds), the step budget and the training settings scaled to it, the
traffic densities it is evaluated at and the reference policies evaluated beside the rows.
``overtake-experiment min2018-table3`` then

1. trains every row's runs, each as its own ``overtake-train`` process (a crash of one leaves
   the others running) with ``--resume-if-found``, at most ``--jobs`` at once;
2. evaluates every run's final checkpoint and every reference policy with ``overtake-eval``,
   greedily, on the same fixed episode seeds at each density;
3. writes the table (``table.md``, ``table.json``) and the learning curves (``curves.png``,
   ``curves.rrd``) into the experiment directory.

Everything is resumable: the experiment may be killed at any moment and started again with the
same command. A run whose checkpoint has reached the budget is not trained again, an unfinished
one continues from its last checkpoint, and each evaluation is cached per (run and checkpoint
step, or reference policy; density) with the settings it was made with. Training and
evaluation processes die with the experiment (Linux), and each holds a lock on its run
directory while it lives, so a restarted experiment never runs a second trainer beside an
earlier one still stopping.

The experiment directory (default ``runs/experiments/<name>``) holds:

- ``experiment.json``: every run's training configuration; a later invocation that would
  train a run differently is refused (choose another ``--out``);
- ``<row>-seed<k>/``: an ``overtake-train`` run directory, plus ``train.log`` (the process's
  output) and ``experiment-lives.jsonl`` (where each life of the run started in its
  ``metrics.jsonl``, so the curves leave out the episodes a resume redid);
- ``evaluations/<run>/<density>-step<N>.json`` and ``evaluations/reference-<policy>/
  <density>.json``: the cached ``overtake-eval`` results, with their logs;
- ``table.md``, ``table.json``, ``curves.png``, ``curves.rrd``.

With ``--ray`` the same tasks are Ray tasks on a cluster whose nodes all see the experiment
directory; a task whose node is lost is retried on another and resumes its runs exactly
(docs/cluster.md).

The package, one idea a module: :mod:`.catalogue` (the experiments as data), :mod:`.plan`
(resolved against a command line), :mod:`.files` and :mod:`.processes` (what the run reads,
writes, locks and starts), :mod:`.run` (the scheduling), :mod:`.launcher` (what runs the
tasks: this machine's processes, or :mod:`.ray_launcher`'s Ray tasks), :mod:`.statistics`,
:mod:`.report` and :mod:`.curves` (the table and curves), :mod:`.evidence` (how each run was
made, and what is kept in git), :mod:`.command` (``main`` and the command line).
"""

from .catalogue import (
    ALGO_NAMES,
    EXPERIMENTS,
    INPUT_NAMES,
    RETIRED,
    Density,
    Experiment,
    ExperimentError,
    Row,
    Schedule,
)
from .command import COMMAND, check_directory, describe_experiments, main
from .evidence import keep_evidence, run_lives
from .files import LIVES_NAME, note_life, training_episodes, training_records, window_rewards
from .plan import (
    ExperimentConfig,
    Plan,
    RunPlan,
    command_args,
    eval_command,
    make_plan,
    reference_policies,
    train_command,
    training_identity,
)
from .report import Outputs, markdown_table
from .run import ExperimentRun
from .statistics import episode_statistics, learning_curves, seed_order, seed_statistics

__all__ = [
    "ALGO_NAMES",
    "COMMAND",
    "EXPERIMENTS",
    "INPUT_NAMES",
    "LIVES_NAME",
    "RETIRED",
    "Density",
    "Experiment",
    "ExperimentConfig",
    "ExperimentError",
    "ExperimentRun",
    "Outputs",
    "Plan",
    "Row",
    "RunPlan",
    "Schedule",
    "check_directory",
    "command_args",
    "describe_experiments",
    "episode_statistics",
    "eval_command",
    "keep_evidence",
    "learning_curves",
    "main",
    "make_plan",
    "markdown_table",
    "note_life",
    "reference_policies",
    "run_lives",
    "seed_order",
    "seed_statistics",
    "train_command",
    "training_episodes",
    "training_identity",
    "training_records",
    "window_rewards",
]
