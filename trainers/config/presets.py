"""What each simulator preset trains with unless told otherwise: its paper's algorithm, inputs,
network, optimiser and hyper-parameters. ``overtake-train --preset NAME`` starts from these
(its ``--help`` shows them), and every one can be overridden by its flag.

- ``min2018`` (Min et al. 2018 and the authors' code): Double DQN with the Dueling network
  (§IV: the three methods "are combined"; the authors' code runs Double + Dueling) on camera
  and LIDAR with the multi-modal network of Table II, Adam 2.5e-4 and the rest of
  :class:`.learner.DQNConfig`'s defaults (an update every 4 steps, the Huber loss, Adam's
  epsilon and the gradient clipping chosen here); the recipe ``notebook`` trains as the
  authors' notebook does.
- ``ho2018`` (Ho 2018, Table 6, and his code, ``songyanho/Reinforcement-Learning-for-Self-
  Driving-Cars``): DQN with a target network (the thesis calls it DDQN but describes a target
  network only) on the occupancy grid with the proposed network of Fig. 5, trained as his
  code trains. From the thesis (Table 6): learning rate 0.0005 (Table 7's runs vary it:
  ``--learning-rate``; his ``config.py``: 0.0001), discount 0.99 (his ``cnn.py``: 0.95),
  4 stacked grids. From the thesis and his code alike: minibatch 32 (``config.py``), replay
  1,000,000 (``MAX_MEM``), learning from 100,000 transitions (``LEARN_START``), epsilon 1 to
  0.1 over 2,000,000 decisions (``EPSILON_GREEDY_MAX_STATES``), a target copy every 10,000
  (``TARGET_NETWORK_UPDATE_FREQUENCY``, counted in decisions as here). From his code:
  an update every decision (``deep_traffic_agent.py`` calls ``optimize`` in every
  ``remember``); TensorFlow's RMSProp with its defaults (``cnn.py``:
  ``tf.train.RMSPropOptimizer(learning_rate)``: decay 0.9, epsilon 1e-10 inside the square
  root, no momentum, not centred, the mean square starting at one; :mod:`.tf_rmsprop`; the
  thesis's "gradient momentum 0.95" is Mnih et al.'s table's, which his code does not
  apply); the squared TD error (``cnn.py``), no gradient clipping; the action stored is the
  one his car drove (``store_applied``: ``players/deep_traffic_player.py`` writes what
  ``car.move`` did over the agent's action, which ``deep_traffic_agent.py``'s ``remember``
  stores; the simulator's ``ego.applied_as_driven`` reports it, and puts it on the action
  stack); an episode's end at its time limit stored as terminal, without a bootstrap
  (``bootstrap_time_limit`` off: ``gui.py`` stores the frame limit's transition with
  ``end_episode``, and ``cnn.py`` bootstraps only where that is not set); the weights from a
  normal of standard deviation 0.02 cut at two, biases zero (``init truncated-normal``,
  ``init_std``: ``cnn.py``'s ``tf.truncated_normal_initializer(stddev=2e-2)`` for every
  layer). Each can be turned back: ``--no-store-applied``, ``--bootstrap-time-limit``,
  ``--init torch``, and ``--set ego.applied_as_driven=false`` for the simulator.
  Evaluation as his code's (``gui.py`` skips frames only while training): a decision every
  frame, 4,000 of them an episode, the frames and actions stacked per decision as in training.
- ``fayjie2018`` (Fayjie et al. 2018, §III.A and Table I): DQN with a target network copied
  every 6,000 steps on the camera and the LIDAR map (``camera-map`` inputs, 4 frames each) with
  the two-stream network (:mod:`.two_stream_network`), learning rate 0.001, discount 0.99,
  epsilon 1 to 0.1, replay 15,000, minibatch 32. Chosen here: Adam (the paper names no
  optimiser), epsilon falling over the first 50,000 of its 100,000+ steps, learning from 1,000
  transitions, the Huber loss and an update every 4 steps.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from ..learning.dqn_config import Algo, DQNConfig
from ..learning.network import Inputs


@dataclass(frozen=True)
class PresetTraining:
    """A preset's training defaults."""

    algo: Algo
    inputs: Inputs
    dqn: DQNConfig
    recipes: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    """named ways of training the preset other than its paper's (``overtake-train --recipe
    NAME``): DQNConfig's fields that each changes"""
    evaluation: tuple[str, ...] = ()
    """simulator overrides (dotted.name=value) under which ``overtake-eval`` evaluates, as
    the paper (or its authors' code) evaluates; ``--no-paper-evaluation`` leaves them out"""


SB3_HIGHWAY_DQN = DQNConfig(
    network="mlp",
    learning_rate=5e-4,
    replay_size=15_000,
    learning_starts=200,
    batch_size=32,
    gamma=0.8,
    train_every=1,
    target_update_steps=50,
    epsilon_start=1.0,
    epsilon_end=0.05,
    epsilon_decay_steps=2_000,
    stack=1,
)

PRESET_TRAINING: dict[str, PresetTraining] = {
    "min2018": PresetTraining(
        algo="dueling",
        inputs="both",
        dqn=DQNConfig(),
        recipes={
            # Min et al.'s notebook (RL_algorithms/Double_Dueling_image_sensor.ipynb), where
            # the paper is silent: Adam with epsilon 0.01, the squared TD error, an update
            # every step (its 50,000 steps of observing before training are the default's
            # learning start). Its 512 LSTM cells are not taken: Table II says 256.
            "notebook": {"adam_eps": 0.01, "loss": "mse", "train_every": 1},
        },
    ),
    "ho2018": PresetTraining(
        algo="dqn",
        inputs="grid",
        dqn=DQNConfig(
            network="proposed",
            optimizer="tf-rmsprop",
            learning_rate=0.0005,
            rmsprop_alpha=0.9,
            rmsprop_eps=1e-10,
            rmsprop_centered=False,
            batch_size=32,
            replay_size=1_000_000,
            learning_starts=100_000,
            gamma=0.99,
            epsilon_start=1.0,
            epsilon_end=0.1,
            epsilon_decay_steps=2_000_000,
            target_update_steps=10_000,
            train_every=1,
            loss="mse",
            grad_clip_norm=0.0,
            stack=4,
            store_applied=True,
            bootstrap_time_limit=False,
            init="truncated-normal",
            init_std=0.02,
        ),
        # His code skips frames only while training (gui.py: `... and is_training`): an
        # evaluated driver decides every frame, over the episode's 4,000 frames.
        evaluation=("episode.frames_per_decision=1", "episode.max_decisions=4000"),
    ),
    # highway-env's scenes: DQN on the Kinematics table as Stable-Baselines3's documented
    # highway-fast recipe trains it (highway-env's docs, scripts/sb3_highway_dqn.py: MlpPolicy
    # with net_arch [256, 256], learning rate 5e-4, buffer 15,000, learning from 200, batch 32,
    # discount 0.8, an update every step, a target copy every 50; SB3's defaults beside them:
    # epsilon 1 to 0.05 over a tenth of its 20,000 steps, the Huber loss, gradients clipped at
    # 10, Adam); no stacking (the table holds velocities).
    **{
        preset: PresetTraining(algo="dqn", inputs="kinematics", dqn=SB3_HIGHWAY_DQN)
        for preset in ("highway-fast", "highway")
    },
    "fayjie2018": PresetTraining(
        algo="dqn",
        inputs="camera-map",
        dqn=DQNConfig(
            network="two-stream",
            learning_rate=0.001,
            gamma=0.99,
            epsilon_start=1.0,
            epsilon_end=0.1,
            replay_size=15_000,
            batch_size=32,
            target_update_steps=6_000,
            learning_starts=1_000,
            epsilon_decay_steps=50_000,
            stack=4,
        ),
    ),
}
