"""Arena groups without the network: membership, rounds, deadlines, shared roads, resets."""

import dataclasses

import numpy as np
import pytest

from overtake.protocol import errors
from overtake.protocol.messages import Actions
from overtake.server.service.arenas import next_to_step
from overtake.server.service.group_state import keep_state, restore_state
from overtake.server.service.groups import Group
from overtake.server.sim import HighwaySim, make_config

QUIET = {"traffic.vehicle_count": 0}


def _actions(group: Group, trainer: str, agents, actions) -> Actions:
    return Actions(
        trainer=trainer,
        ticket=group.members[trainer].ticket,
        group=group.group_id,
        round=group.round,
        agents=np.asarray(agents, dtype=np.int32),
        actions=np.asarray(actions, dtype=np.int64),
    )


def _shared(agents: int = 3, overrides=None) -> Group:
    group = Group.open(0, "srv", [7], "min2018", dict(overrides or QUIET), agents, seed=1)
    group.claim("a", 0, 1, fresh=True)
    return group


def test_unclaimed_cars_are_off_the_road_and_unseen():
    group = _shared()
    assert group.sim.agents_present()[0].tolist() == [True, False, False]
    # Agent 0's LIDAR sees only the rails: the free slots' cars are nowhere.
    lidar = group.sim.observe()["lidar"][0, 0]
    empty = HighwaySim(make_config(overrides=QUIET), agents_per_arena=1)
    empty.reset(seeds=[1])
    here = group.sim.state
    empty.state.x_m[0, 0], empty.state.y_m[0, 0] = here.x_m[0, 0], here.y_m[0, 0]
    empty.state.lane[0, 0] = empty.state.target_lane[0, 0] = group.sim.state.lane[0, 0]
    np.testing.assert_array_equal(lidar, empty.observe()["lidar"][0, 0])


def test_a_joined_car_is_placed_clear_of_the_others_and_seen_by_them():
    group = _shared(overrides={})
    group.claim("b", 0, 1, fresh=False)
    st = group.sim.state
    assert group.sim.agents_present()[0].tolist() == [True, True, False]
    assert (group.members["b"].slots[0] == [False, True, False]).all()
    # Clear of every other car: no box within an IDM gap in its lane.
    same_lane = st.active[0] & (st.lane[0] == st.lane[0, 1])
    same_lane[1] = False
    gaps = np.abs(st.x_m[0, same_lane] - st.x_m[0, 1])
    assert gaps.size == 0 or gaps.min() > group.sim.config.traffic.vehicle_length_m + 2.0
    # Agent 0 now sees a car where agent 1 is (some ray shorter than on an empty road).
    before = _shared(overrides={}).sim.observe()["lidar"][0, 0]
    assert not np.array_equal(group.sim.observe()["lidar"][0, 0], before)


def test_a_round_waits_for_every_member_then_steps_everyone():
    group = _shared()
    group.claim("b", 0, 1, fresh=False)
    group.accept(_actions(group, "a", [0], [1]), deadline_s=60.0)
    assert not group.ready(now=0.0)
    group.accept(_actions(group, "b", [1], [2]), deadline_s=60.0)
    assert group.ready(now=0.0)
    steps = group.step()
    assert set(steps) == {"a", "b"}
    assert steps["a"].agents.tolist() == [0] and steps["b"].agents.tolist() == [1]
    assert steps["a"].action_applied.tolist() == [1] and steps["b"].action_applied.tolist() == [2]
    assert group.round == 1 and steps["a"].round == 1


def test_the_deadline_steps_without_the_late_member_with_keep():
    group = _shared()
    group.claim("b", 0, 1, fresh=False)
    group.accept(_actions(group, "a", [0], [1]), deadline_s=5.0)
    assert group.deadline is not None
    assert not group.ready(now=group.deadline - 0.01)
    assert group.ready(now=group.deadline)
    steps = group.step()
    assert steps["b"].late.tolist() == [True] and steps["b"].action_applied.tolist() == [0]
    assert steps["a"].late.tolist() == [False]
    assert group.late_agents == 1 and group.status().late_agents == 1


def test_nobody_acting_means_nobody_waits():
    group = _shared()
    assert not group.ready(now=1e12)  # no deadline runs until someone has acted


def test_actions_are_checked_against_what_the_trainer_owns():
    group = _shared()
    group.claim("b", 0, 1, fresh=False)
    with pytest.raises(errors.NotOwner, match="belong to another trainer"):
        group.accept(_actions(group, "a", [1], [0]), deadline_s=1.0)
    with pytest.raises(errors.BadAction, match="0..2"):
        group.accept(_actions(group, "a", [5], [0]), deadline_s=1.0)
    stale = Actions(
        trainer="a",
        ticket=group.members["a"].ticket,
        group=0,
        round=3,
        agents=np.array([0], np.int32),
        actions=np.array([0]),
    )
    with pytest.raises(errors.BadAction, match="round 3.*round 0"):
        group.accept(stale, deadline_s=1.0)
    forged = Actions(
        trainer="a",
        ticket=b"\0" * 16,
        group=0,
        round=0,
        agents=np.array([0], np.int32),
        actions=np.array([0]),
    )
    with pytest.raises(errors.NotOwner, match="wrong ticket"):
        group.accept(forged, deadline_s=1.0)
    with pytest.raises(errors.NotOwner, match="no agents"):
        group.member("c", b"\0" * 16)


def test_in_a_shared_arena_only_the_crashed_car_restarts():
    group = _shared(agents=2, overrides=QUIET)
    group.claim("b", 0, 1, fresh=False)
    st = group.sim.state
    # Put b's car right behind a's, much faster: it rear-ends a.
    st.lane[0, :2] = st.target_lane[0, :2] = 1
    st.y_m[0, :2] = 1.5 * group.sim.road.lane_width_m
    st.x_m[0, :2] = [10.0, 5.0]
    st.speed_mps[0, :2] = [10.0, 30.0]
    for member in ("a", "b"):
        group.accept(
            _actions(group, member, group.members[member].slots.reshape(-1).nonzero()[0], [0]),
            deadline_s=1.0,
        )
    steps = group.step()
    assert steps["a"].terminated.tolist() == [True] and steps["b"].terminated.tolist() == [True]
    x_before = st.x_m[0, :2].copy()
    for member in ("a", "b"):
        group.accept(
            _actions(group, member, group.members[member].slots.reshape(-1).nonzero()[0], [0]),
            deadline_s=1.0,
        )
    steps = group.step()
    # Both restarted: reward 0, no flags, fresh counters, and placed behind where they were.
    for member in ("a", "b"):
        assert steps[member].reward.tolist() == [0.0]
        assert not steps[member].ended.any()
        assert steps[member].metrics[0].tolist()[-1] == 0  # decisions of the new episode
    assert (st.x_m[0, :2] < x_before.max()).all()
    assert group.sim.agents_present()[0].tolist() == [True, True]


def test_reset_alone_reseeds_but_shared_only_respawns_the_requester():
    alone = Group.open(0, "srv", [0, 1], "min2018", {}, 1, seed=5)
    alone.claim("a", 0, 1, fresh=True)
    alone.claim("a", 1, 1, fresh=True)
    ticket = alone.members["a"].ticket
    first = alone.reset("a", ticket, (0, 1), (11, 12))
    again = alone.reset("a", ticket, (0, 1), (11, 12))
    for name in first.observations:
        np.testing.assert_array_equal(first.observations[name], again.observations[name])

    shared = _shared(overrides={})
    shared.claim("b", 0, 1, fresh=False)
    a_x = shared.sim.state.x_m[0, 0]
    shared.reset("b", shared.members["b"].ticket, (0,), (99,))
    assert shared.sim.state.x_m[0, 0] == a_x, "a's car did not move when b reset"
    with pytest.raises(errors.UnknownArena):
        shared.reset("b", shared.members["b"].ticket, (3,), (None,))


def test_leaving_takes_the_cars_off_and_frees_the_slot():
    group = _shared()
    group.claim("b", 0, 2, fresh=False)
    with pytest.raises(errors.ServerFull, match="0 free agent slot"):
        group.claim("c", 0, 1, fresh=False)
    group.leave("b")
    assert group.sim.agents_present()[0].tolist() == [True, False, False]
    group.claim("c", 0, 2, fresh=False)
    assert set(group.members) == {"a", "c"}


def _all_act(group: Group) -> None:
    for name, member in group.members.items():
        agents = np.flatnonzero(member.slots & ~group.ended)
        group.accept(_actions(group, name, agents, np.zeros(agents.size, np.int64)), 1.0)


def test_a_car_that_ended_as_its_trainer_left_stays_off_the_road():
    group = _shared(agents=2, overrides=QUIET)
    group.claim("b", 0, 1, fresh=False)
    group.ended[0, 1] = True  # b's episode just ended...
    group.leave("b")  # ...and b left before its next action
    for _ in range(3):
        _all_act(group)
        group.step()
        assert group.sim.agents_present()[0].tolist() == [True, False]


def test_a_respawned_car_is_not_an_overtake_for_the_others():
    group = _shared(agents=2, overrides=QUIET)
    group.claim("b", 0, 1, fresh=False)
    st = group.sim.state
    st.x_m[0, 1] = st.x_m[0, 0] + 80.0  # b far ahead of a
    group.sim.tracker.start(st, np.ones_like(st.active))
    group.ended[0, 1] = True  # b restarts behind a on the next round
    overtake = group.spec.reward_terms.index("overtake")
    overtakes = group.spec.metric_fields.index("overtakes")
    for _ in range(2):
        _all_act(group)
        steps = group.step()
        assert steps["a"].reward_terms[0, overtake] == 0.0, "a was paid for b's respawn"
        assert steps["a"].metrics[0, overtakes] == 0  # a's overtakes this episode


def test_agents_left_out_of_a_trainers_actions_are_marked_late():
    group = Group.open(0, "srv", [0, 1], "min2018", dict(QUIET), 1, seed=3)
    group.claim("a", 0, 1, fresh=True)
    group.claim("a", 1, 1, fresh=True)
    group.accept(_actions(group, "a", [0], [1]), deadline_s=1.0)
    steps = group.step()["a"]
    assert steps.late.tolist() == [False, True]
    assert steps.action_applied.tolist() == [1, 0]


@pytest.mark.parametrize("seed", range(10))
def test_respawn_takes_the_nearest_free_spot_over_all_lanes(seed):
    group = Group.open(0, "srv", [7], "min2018", dict(QUIET), 2, seed=seed)
    group.claim("a", 0, 1, fresh=True)
    group.claim("b", 0, 1, fresh=False)
    # On an empty road some lane is free 30 m behind a: whatever lane order the arena's
    # generator draws, b lands 30 m back rather than farther back in the first lane tried.
    st = group.sim.state
    assert st.x_m[0, 1] == st.x_m[0, 0] - 30.0


def _retiring(group: Group, trainer: str, agents, actions, retire) -> Actions:
    return dataclasses.replace(
        _actions(group, trainer, agents, actions), retire=np.asarray(retire, dtype=np.int32)
    )


def test_a_retired_car_stays_off_the_road_and_is_not_late_until_its_arena_resets():
    group = _shared(agents=3)
    group.claim("a", 0, 1, fresh=False)  # a drives cars 0 and 1
    group.claim("b", 0, 1, fresh=False)  # b drives car 2
    # a retires car 1: it leaves before the round and is not restarted or counted late.
    group.accept(_retiring(group, "a", [0], [1], [1]), deadline_s=1.0)
    group.accept(_actions(group, "b", [2], [0]), deadline_s=1.0)
    steps = group.step()
    assert group.sim.agents_present()[0].tolist() == [True, False, True]
    assert steps["a"].late.tolist() == [False, False] and group.late_agents == 0
    assert steps["a"].action_applied.tolist()[1] == -1 and steps["a"].reward[1] == 0.0
    for _ in range(3):
        group.accept(_actions(group, "a", [0], [0]), deadline_s=1.0)
        group.accept(_actions(group, "b", [2], [0]), deadline_s=1.0)
        group.step()
    assert group.sim.agents_present()[0].tolist() == [True, False, True]
    assert group.late_agents == 0
    # Retiring another trainer's car, or a car of no group slot, is refused by name.
    with pytest.raises(errors.NotOwner, match=r"agents \[2\] .* may retire only its own"):
        group.accept(_retiring(group, "a", [0], [0], [2]), deadline_s=1.0)
    with pytest.raises(errors.BadAction, match=r"asked to retire \[9\]"):
        group.accept(_retiring(group, "a", [0], [0], [9]), deadline_s=1.0)
    # a's reset (shared road: a respawn) brings its retired car back.
    group.reset("a", group.members["a"].ticket, (0,), (None,))
    assert group.sim.agents_present()[0].tolist() == [True, True, True]
    assert not group.retired.any()


def test_a_car_retired_just_after_its_episode_ended_is_not_restarted():
    group = _shared(agents=2, overrides=QUIET)
    group.claim("a", 0, 1, fresh=False)
    st = group.sim.state
    # Car 1 right behind car 0, much faster: it rear-ends car 0 (both of a's cars end).
    st.lane[0, :2] = st.target_lane[0, :2] = 1
    st.y_m[0, :2] = 1.5 * group.sim.road.lane_width_m
    st.x_m[0, :2] = [10.0, 5.0]
    st.speed_mps[0, :2] = [10.0, 30.0]
    group.accept(_actions(group, "a", [0, 1], [0, 0]), deadline_s=1.0)
    assert group.step()["a"].terminated.tolist() == [True, True]
    group.accept(_retiring(group, "a", [0], [0], [1]), deadline_s=1.0)
    steps = group.step()
    # Car 0 restarted (Gymnasium's autoreset); car 1 left instead.
    assert group.sim.agents_present()[0].tolist() == [True, False]
    assert not steps["a"].ended.any() and not group.ended.any()


def _serve_on_virtual_time(pick_pass, steps: int) -> list[int]:
    """Four groups of one trainer each on a server whose group step takes 1 time unit, each
    trainer answering 0.5 units after its observations leave (the server is the bottleneck, as
    on 2 cores). ``pick_pass(groups, now)`` gives the groups the server steps next, in order;
    answers arriving meanwhile wait for the next pick. Returns the steps each group got."""
    groups = [Group.open(i, "srv", [i], "min2018", dict(QUIET), 1, seed=i) for i in range(4)]
    for group in groups:
        group.claim(f"t{group.group_id}", 0, 1, fresh=True)
    answers = {group.group_id: 0.0 for group in groups}  # when each trainer's actions arrive
    now, done = 0.0, 0
    while done < steps:
        for group in groups:
            at = answers.get(group.group_id)
            if at is not None and at <= now:
                del answers[group.group_id]
                group.accept(_actions(group, f"t{group.group_id}", [0], [0]), deadline_s=1e9)
        chosen = pick_pass(groups, now)
        if not chosen:
            now = min(answers.values())
            continue
        for group in chosen:
            group.step()
            now += 1.0
            answers[group.group_id] = now + 0.5
            done += 1
    return [group.rounds_done for group in groups]


def test_groups_of_equal_trainers_get_equal_shares_of_a_busy_server():
    def one_at_a_time(groups, now):
        group = next_to_step(groups, now)
        return [] if group is None else [group]

    shares = _serve_on_virtual_time(one_at_a_time, steps=120)
    assert max(shares) - min(shares) <= 1, shares

    # What the server did before, every ready group per pass in a fixed order, gives two of
    # the four trainers half the steps of the other two in this very model.
    def every_ready_in_order(groups, now):
        return [g for g in groups if g.ready(now)]

    before = sorted(_serve_on_virtual_time(every_ready_in_order, steps=120))
    assert before[2] >= 1.8 * before[1], before


# --- a kept state (protocol 1.8) ----------------------------------------------------------------


def _alone(preset: str = "min2018", seed: int = 1, arenas: int = 2) -> Group:
    group = Group.open(0, "srv", list(range(arenas)), preset, dict(QUIET), 1, seed=seed)
    for arena in range(arenas):
        group.claim("a", arena, 1, fresh=True)
    return group


def _rounds(group: Group, actions: np.ndarray) -> list:
    out = []
    ticket = group.members["a"].ticket
    agents = np.arange(group.shape[0] * group.shape[1], dtype=np.int32)
    for row in actions:
        group.accept(
            Actions(trainer="a", ticket=ticket, group=0, round=group.round, agents=agents,
                    actions=row.astype(np.int64)),
            10.0,
        )  # fmt: skip
        out.append(group.step()["a"])
    return out


def test_a_kept_state_put_into_another_group_plays_the_rounds_that_followed_it():
    actions = np.random.default_rng(4).integers(0, 5, (30, 2))
    group = _alone()
    _rounds(group, actions[:10])
    kept = keep_state(group, "a", group.members["a"].ticket)
    expected = _rounds(group, actions[10:])
    other = _alone(seed=77)  # another road entirely
    _rounds(other, actions[:3])
    steps = restore_state(other, "a", other.members["a"].ticket, kept.state)
    assert steps.reward.tolist() == [0.0, 0.0] and not steps.terminated.any()
    for got, want in zip(_rounds(other, actions[10:]), expected, strict=True):
        for name in want.observations:
            np.testing.assert_array_equal(got.observations[name], want.observations[name])
        np.testing.assert_array_equal(got.reward, want.reward)
        np.testing.assert_array_equal(
            got.terminated | got.truncated, want.terminated | want.truncated
        )
        np.testing.assert_array_equal(got.metrics, want.metrics)


def test_a_state_is_kept_only_for_a_trainer_alone_between_rounds_and_put_only_where_it_fits():
    group = _alone()
    ticket = group.members["a"].ticket
    kept = keep_state(group, "a", ticket)
    with pytest.raises(errors.WrongTicket):
        keep_state(group, "a", b"x" * 16)
    # Actions waiting: not between rounds.
    group.accept(
        Actions(trainer="a", ticket=ticket, group=0, round=group.round,
                agents=np.array([0], np.int32), actions=np.array([0], np.int64)),
        10.0,
    )  # fmt: skip
    with pytest.raises(errors.BadAction, match="between rounds"):
        keep_state(group, "a", ticket)
    with pytest.raises(errors.BadAction, match="between rounds"):
        restore_state(group, "a", ticket, kept.state)
    # Another configuration, another size, or not a state at all: refused, nothing changed.
    for other in (_alone("ho2018"), _alone(arenas=3)):
        before = other.sim.snapshot().arrays["x_m"].copy()
        with pytest.raises(errors.BadConfig, match="cannot take this state"):
            restore_state(other, "a", other.members["a"].ticket, kept.state)
        np.testing.assert_array_equal(other.sim.state.x_m, before)
    fresh = _alone()
    with pytest.raises(errors.BadConfig, match="not a group snapshot"):
        restore_state(fresh, "a", fresh.members["a"].ticket, b"garbage")
    # A shared group: another trainer's episodes would be rewound.
    shared = _shared()
    with pytest.raises(errors.NotOwner, match="owns every car"):
        keep_state(shared, "a", shared.members["a"].ticket)
