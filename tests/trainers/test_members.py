"""Members: several runs trained in one process as members of one learner
(trainers/run/members_run.py, trainers/learning/member_learner.py, member_network.py,
member_optim.py).

A member is a lone run: an update of member k equals a lone learner's update on the same batch
(float rounding apart), for every network kind and optimiser; a member's run directory is a
lone run's (a lone learner loads its checkpoint); a stopped batch of members resumes exactly;
bad members are refused in one line before any work."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from overtake.cli import UsageError
from overtake.client.episodes.scenario import Scenario, Where
from overtake.trainers.experiment.evidence import provenance_line, run_lives
from overtake.trainers.learning.dqn_config import ALGOS, DQNConfig
from overtake.trainers.learning.grid_network import GridNetworkShape
from overtake.trainers.learning.learner import DQNLearner
from overtake.trainers.learning.member_learner import MembersLearner
from overtake.trainers.learning.member_network import member_state, stacked_network
from overtake.trainers.learning.mlp_network import MlpNetworkShape
from overtake.trainers.learning.network import NetworkShape
from overtake.trainers.learning.replay_memory import ReplayBatch
from overtake.trainers.learning.two_stream_network import TwoStreamShape
from overtake.trainers.run.checkpoint import CHECKPOINT_NAME, load_checkpoint
from overtake.trainers.train import TrainConfig, train_members
from overtake.trainers.train import main as train

from .test_exact_resume import StopAfter, assert_same_weights, online_weights

BATCH = 8
ACTIONS = 5


def _frames(rng: np.random.Generator, inputs: str, shape) -> dict[str, np.ndarray]:
    """A batch of stacked observations for a network of ``inputs``."""
    if inputs == "grid":
        cells, lanes = shape.grid_hw
        return {
            "grid": rng.integers(-1, 2, (BATCH, shape.stack, cells, lanes)).astype(np.int8),
            "actions": rng.integers(0, ACTIONS, (BATCH, shape.action_history)).astype(np.int64),
        }
    if inputs == "kinematics":
        return {"kinematics": rng.random((BATCH, shape.stack, *shape.table_hw), np.float32)}
    if inputs == "camera-map":
        h, w, c = shape.camera_hwc
        return {
            "camera": rng.integers(0, 256, (BATCH, shape.stack, h, w, c)).astype(np.uint8),
            "lidar_map": rng.integers(0, 256, (BATCH, shape.stack, *shape.map_hw)).astype(np.uint8),
        }
    return {
        "camera": rng.integers(0, 256, (BATCH, shape.stack, *shape.camera_hw)).astype(np.uint8),
        "lidar": (rng.random((BATCH, shape.stack, shape.lidar_rays)) * 80).astype(np.float32),
        "ego": rng.random((BATCH, shape.ego_size)).astype(np.float32),
    }


def _batch(rng: np.random.Generator, inputs: str, shape, weighted: bool = False) -> ReplayBatch:
    return ReplayBatch(
        obs=_frames(rng, inputs, shape),
        next_obs=_frames(rng, inputs, shape),
        action=rng.integers(0, ACTIONS, BATCH),
        reward=rng.normal(size=BATCH).astype(np.float32),
        terminated=rng.random(BATCH) < 0.2,
        steps=np.ones(BATCH, dtype=np.int64),
        next_mask=(rng.random((BATCH, ACTIONS)) < 0.8).astype(np.int8),
        weight=rng.random(BATCH).astype(np.float32) if weighted else None,
        leaves=np.arange(BATCH) if weighted else None,
    )


# Each network kind, with an optimiser and head its presets use; small sizes for speed.
KINDS = {
    "grid-proposed": (
        "grid",
        GridNetworkShape((12, 3), 4, ACTIONS, 4),
        "dqn",
        dict(network="proposed", optimizer="tf-rmsprop", rmsprop_alpha=0.9, rmsprop_eps=1e-10,
             rmsprop_centered=False, loss="mse", grad_clip_norm=0.0),
    ),
    "grid-baseline": (
        "grid",
        GridNetworkShape((12, 3), 4, ACTIONS, 4),
        "dueling",
        dict(network="baseline", optimizer="rmsprop"),
    ),
    "mlp": ("kinematics", MlpNetworkShape((5, 5), ACTIONS, 1, (32, 32)), "dqn",
            dict(network="mlp", optimizer="adam", grad_clip_norm=10.0)),
    "camera-lidar-lstm": (
        "both",
        NetworkShape((36, 36), 16, 6, ACTIONS, 2, 80.0, (1.0,) * 6),
        "qr",
        dict(network="multimodal", optimizer="adam", lstm_cells=8, hidden_units=16,
             quantiles=3, grad_clip_norm=1.0),
    ),
    "two-stream": (
        "camera-map",
        TwoStreamShape((36, 36, 3), (36, 36), ACTIONS, 2),
        "ddqn",
        dict(network="two-stream", optimizer="adam", grad_clip_norm=10.0),
    ),
}  # fmt: skip


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_an_update_of_member_k_is_a_lone_learners_update_on_the_same_batch(kind: str) -> None:
    """Three members of different learning rates (and Adam's epsilon), each updated twice on
    its own batch, end where three lone learners of the same seeds and settings end on the
    same batches: within 1e-5 of each weight (float rounding: the batched products sum in
    another order), and with the same loss; the target copy and the optimiser's moments as
    well (a lone learner loading member k's state dict goes on as the lone one does)."""
    inputs, shape, algo, settings = KINDS[kind]
    configs = [
        DQNConfig(**settings, learning_rate=rate, adam_eps=eps, batch_size=BATCH)
        for rate, eps in ((1e-3, 1e-8), (3e-4, 1e-4), (5e-3, 1e-2))
    ]
    seeds = [0, 7, 7]  # a seed may repeat: rows of a table share their seeds
    members = MembersLearner(shape, inputs, configs, ALGOS[algo], seeds)  # type: ignore[arg-type]
    lones = []
    for seed, config in zip(seeds, configs, strict=True):
        torch.manual_seed(seed)
        lones.append(DQNLearner(shape, inputs, config, ALGOS[algo]))  # type: ignore[arg-type]
    rng = np.random.default_rng(1)
    for _ in range(2):
        batches = [_batch(rng, inputs, shape) for _ in configs]
        stats = members.update(batches)
        expected = [lone.update(batch) for lone, batch in zip(lones, batches, strict=True)]
        for got, want in zip(stats, expected, strict=True):
            assert got["loss"] == pytest.approx(want["loss"], rel=1e-4, abs=1e-6)
            assert got["q_taken"] == pytest.approx(want["q_taken"], rel=1e-4, abs=1e-6)
    members.sync_target([1])
    lones[1].sync_target()
    for k, lone in enumerate(lones):
        state = members.member_state_dict(k)
        for part in ("online", "target"):
            want = getattr(lone, part).state_dict()
            assert state[part].keys() == want.keys()
            for name, value in want.items():
                assert torch.allclose(state[part][name], value, atol=1e-5, rtol=0), (k, part, name)
        # The member's state is a lone learner's: loaded into one, it steps as the lone does.
        twin = DQNLearner(shape, inputs, configs[k], ALGOS[algo])  # type: ignore[arg-type]
        twin.load_state_dict(state)
        batch = _batch(rng, inputs, shape)
        assert twin.update(batch)["loss"] == pytest.approx(lone.update(batch)["loss"], rel=1e-3)


def test_the_members_network_acts_as_the_lone_networks_do() -> None:
    """The stacked network's output on every member's rows is each lone network's output, and
    each member's state dict is its lone network's, bit for bit."""
    inputs, shape, _, settings = KINDS["grid-proposed"]
    lones = []
    for seed in (3, 4):
        torch.manual_seed(seed)
        learner = DQNLearner(shape, inputs, DQNConfig(**settings), ALGOS["dqn"])  # type: ignore[arg-type]
        lones.append(learner.online)
    stacked = stacked_network(lones)
    rng = np.random.default_rng(0)
    frames = [_frames(rng, inputs, shape) for _ in lones]
    rows = [torch.as_tensor(np.concatenate([f[n] for f in frames])) for n in ("grid", "actions")]
    with torch.no_grad():
        out = stacked(*rows)
        want = torch.cat([net(*(torch.as_tensor(f[n]) for n in ("grid", "actions")))
                          for net, f in zip(lones, frames, strict=True)])  # fmt: skip
    assert torch.allclose(out, want, atol=1e-6)
    for k, lone in enumerate(lones):
        assert_same_weights(member_state(stacked, k), lone.state_dict())


def test_a_member_that_sits_an_update_out_is_left_as_it_was() -> None:
    inputs, shape, algo, settings = KINDS["mlp"]
    members = MembersLearner(
        shape, inputs, [DQNConfig(**settings, batch_size=BATCH)] * 2, ALGOS[algo], [0, 1]
    )  # type: ignore[arg-type]
    before = members.member_state_dict(1)
    rng = np.random.default_rng(0)
    stats = members.update([_batch(rng, inputs, shape), None])
    assert stats[1] == {} and "loss" in stats[0]
    after = members.member_state_dict(1)
    assert_same_weights(after["online"], before["online"])
    assert int(members.updates[1]) == 0 and int(members.updates[0]) == 1


def test_members_whose_networks_differ_are_refused_in_one_line() -> None:
    inputs, shape, algo, settings = KINDS["grid-proposed"]
    other = {**settings, "network": "baseline"}
    with pytest.raises(ValueError, match="members must share network"):
        MembersLearner(
            shape, inputs, [DQNConfig(**settings), DQNConfig(**other)], ALGOS[algo], [0, 1]
        )  # type: ignore[arg-type]


def _highway_run(run_dir: Path, **changes) -> TrainConfig:
    """highway-fast's recipe, short: 2 arenas, learning from step 40, a checkpoint every 60."""
    config = TrainConfig.for_preset(
        "highway-fast",
        run_dir=run_dir,
        num_envs=2,
        total_steps=240,
        progress=False,
        log_every=40,
        checkpoint_every=60,
        scenario=Scenario(set=("episode.max_decisions=25",)),
    )
    dqn = dataclasses.replace(config.dqn, learning_starts=40, replay_size=400)
    return dataclasses.replace(config, dqn=dqn, **changes)


def test_a_member_run_directory_is_a_lone_runs_and_its_run_matches_the_lone_run(tmp_path) -> None:
    """``--seeds 0 1`` trains two runs in seed-0 and seed-1, each a lone run's directory: its
    checkpoint names its own seed and loads into a lone learner; member 0's training is the
    lone run of seed 0 (the same episodes while the networks agree; its losses within
    float rounding's drift)."""
    members = train(_highway_run(tmp_path / "both", seeds=(0, 1)))
    assert [Path(m["run_dir"]).name for m in members["members"]] == ["seed-0", "seed-1"]
    lone = tmp_path / "lone"
    train(_highway_run(lone, seed=0))
    member = tmp_path / "both" / "seed-0"
    checkpoint = load_checkpoint(member / CHECKPOINT_NAME)
    assert checkpoint.step == 240 and checkpoint.config["seed"] == 0
    checkpoint.make_learner()  # a lone learner takes a member's state
    # Its provenance says it trained as a member (the experiments' "How each run was made").
    lives = run_lives(member, 240)
    assert [life["members"] for life in lives] == [2]
    assert "one of 2 members of one learner" in provenance_line(lives)
    assert run_lives(tmp_path / "lone", 240)[0]["members"] == 1
    assert load_checkpoint(tmp_path / "both" / "seed-1" / CHECKPOINT_NAME).config["seed"] == 1

    def lines(run_dir: Path, kind: str) -> list[dict]:
        records = [
            json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()
        ]
        return [r for r in records if r["kind"] == kind]

    member_losses = [r["loss"] for r in lines(member, "train")]
    lone_losses = [r["loss"] for r in lines(lone, "train")]
    assert len(member_losses) == len(lone_losses)
    assert member_losses[1] == pytest.approx(lone_losses[1], rel=1e-3)
    first = lines(lone, "episode")[0]
    assert lines(member, "episode")[0]["return"] == pytest.approx(first["return"])


def test_a_stopped_batch_of_members_resumes_bit_for_bit(tmp_path) -> None:
    """Two members stopped part-way and resumed end with the weights of the two never
    stopped, bit for bit, each."""
    never = tmp_path / "never"
    train(_highway_run(never, seeds=(0, 1)))
    stopped = tmp_path / "stopped"
    summary = train(_highway_run(stopped, seeds=(0, 1)), stop=StopAfter(2 * 45))
    assert all(m["stopped"] for m in summary["members"])
    train(_highway_run(stopped, seeds=(0, 1), resume=True))
    for seed in (0, 1):
        assert_same_weights(
            online_weights(stopped / f"seed-{seed}"), online_weights(never / f"seed-{seed}")
        )


def test_bad_members_are_refused_before_any_work(tmp_path) -> None:
    with pytest.raises(UsageError, match="seed 1 more than once"):
        train(_highway_run(tmp_path / "a", seeds=(0, 1, 1)))
    assert not (tmp_path / "a").exists()
    base = _highway_run(tmp_path / "b")
    differ = [
        dataclasses.replace(base, seed=0, run_dir=tmp_path / "b0"),
        dataclasses.replace(base, seed=1, run_dir=tmp_path / "b1", num_envs=3),
    ]
    with pytest.raises(UsageError, match="lock-step.*num_envs"):
        train_members(differ)
    # --resume --seeds into a directory that holds other seeds' runs.
    train(_highway_run(tmp_path / "c", seeds=(0, 1), total_steps=60))
    with pytest.raises(UsageError, match="other seeds too.*seed-1"):
        train(_highway_run(tmp_path / "c", seeds=(0,), resume=True))


def test_members_train_on_a_server_as_in_process(tmp_path, start_server) -> None:
    """With --connect each member's arenas are on the server (every member's actions go out
    before any member's round comes back); the server's rounds are the in-process ones, so
    each member ends with the in-process member's weights, bit for bit."""
    server = start_server("members")
    remote = tmp_path / "remote"
    summary = train(_highway_run(remote, seeds=(0, 1), where=Where(connect=(server.endpoint,))))
    assert [m["steps"] for m in summary["members"]] == [240, 240]
    here = tmp_path / "here"
    train(_highway_run(here, seeds=(0, 1)))
    for seed in (0, 1):
        assert_same_weights(
            online_weights(remote / f"seed-{seed}"), online_weights(here / f"seed-{seed}")
        )


def test_a_member_ahead_of_the_others_waits_for_them(tmp_path) -> None:
    """A batch resumed where one member's checkpoint is further on (it trained alone for a
    while): every member reaches its budget, and the one that got there first stops storing
    and learning while the others go on."""
    folder = tmp_path / "batch"
    train(_highway_run(folder / "seed-1", seed=1, total_steps=120))
    summary = train(_highway_run(folder, seeds=(0, 1), resume_if_found=True))
    steps = [m["steps"] for m in summary["members"]]
    assert steps == [240, 240]
    assert summary["members"][1]["resumed_at_step"] == 120
    for seed in (0, 1):
        assert load_checkpoint(folder / f"seed-{seed}" / CHECKPOINT_NAME).step == 240


def test_in_process_members_of_one_simulator_step_in_one_engine(tmp_path) -> None:
    """Members of one simulator configuration get shares of one engine (one simulator call a
    round for all); members whose simulators differ each open their own."""
    from overtake.envs.shares import EngineShare
    from overtake.trainers.train import open_members_envs

    base = _highway_run(tmp_path)
    alike = [dataclasses.replace(base, seed=s, run_dir=tmp_path / f"s{s}") for s in (0, 1, 2)]
    envs = open_members_envs(alike)
    try:
        engines = [env.simulator.parts[0] for env in envs]
        assert all(isinstance(e, EngineShare) for e in engines)
        assert len({id(e.shared) for e in engines}) == 1  # type: ignore[attr-defined]
        assert [e.first_arena for e in engines] == [0, 2, 4]  # type: ignore[attr-defined]
    finally:
        for env in envs:
            env.close()
    longer = dataclasses.replace(alike[1].scenario, set=("episode.max_decisions=30",))
    other = dataclasses.replace(alike[1], scenario=longer)
    envs = open_members_envs([alike[0], other])
    try:
        assert not any(isinstance(env.simulator.parts[0], EngineShare) for env in envs)
    finally:
        for env in envs:
            env.close()
