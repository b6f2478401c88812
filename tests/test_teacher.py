"""DAgger's teacher: labels start shortest paths, follow the lockstep order, and do not depend on
what the first screen cannot show."""

import itertools
import math

import numpy as np
import pytest
import torch

from formation.config import GameConfig
from formation.game import MOVES, BatchedGame
from formation.learn.teacher import Teacher, lockstep_order
from formation.planner import shortest_first_moves, shortest_path, shortest_path_counts

SMALL = GameConfig.from_setting(None, height=9, width=9, n_obstacles=1)


def scenarios(config, seeds):
    game = BatchedGame(config, batch_size=len(seeds))
    out = []
    for i, seed in enumerate(seeds):
        game.reset(seed=seed, mask=np.arange(len(seeds)) == i)
        out.append(game.scenario(i))
    return out


def steps_after(config, scenario, joint):
    """Length of the shortest path left after playing ``joint`` (0 if it wins, None if it loses)."""
    game = BatchedGame(config, batch_size=1)
    game.load([scenario])
    game.step(np.array([joint]))
    if game.done[0]:
        return 0 if game.success[0] else None
    path = shortest_path(game.scenario(0), config=config)
    return None if path is None else len(path)


def labelled_states(teacher, n):
    """(scenario, the teacher's label, the shortest path's length after it) for the first ``n``
    seeds' starts of SMALL that have a label."""
    for scenario in scenarios(SMALL, range(n)):
        joint = teacher.label(scenario)
        if joint is not None:
            yield scenario, joint, steps_after(SMALL, scenario, joint)


def order_at(scenario):
    """The teacher's lockstep order for a state of SMALL (sideways towards the destination first)."""
    return lockstep_order(2, 2 if scenario.leader[1] < SMALL.destination[1] else 1)


@pytest.mark.parametrize("n_agents,toward", [(2, 1), (2, 2), (3, 1)])
def test_lockstep_order_lists_every_joint_action_once_lockstep_first(n_agents, toward):
    order = lockstep_order(n_agents, toward)
    assert sorted(order) == sorted(itertools.product(range(4), repeat=n_agents))
    assert order[:4] == [(m,) * n_agents for m in (0, toward, 3 - toward, 3)]
    assert order[4][0] == 0  # then the leader's forward move first


def test_toward_first_order_ranks_the_move_towards_the_destination_before_forward():
    order = lockstep_order(2, 2, toward_first=True)
    assert sorted(order) == sorted(itertools.product(range(4), repeat=2))
    assert order[:4] == [(2, 2), (0, 0), (1, 1), (3, 3)]
    toward, lockstep = Teacher(SMALL, slack=200, order="toward"), Teacher(SMALL, slack=200, order="lockstep")
    both = 0
    for scenario in scenarios(SMALL, range(30)):  # the spec's start: left of the destination's column
        found = shortest_first_moves(scenario, config=SMALL)
        if found is not None and {(0, 0), (2, 2)} <= set(found[1]):  # straight on and right both optimal
            both += 1
            assert lockstep.label(scenario) == (0, 0) and toward.label(scenario) == (2, 2)
    assert both >= 5


def test_planner_order_labels_with_the_planners_first_action():
    teacher = Teacher(SMALL, slack=200)
    for scenario in scenarios(SMALL, range(10)):
        path = shortest_path(scenario, config=SMALL)
        assert teacher.label(scenario) == (None if path is None else tuple(int(a) for a in path[0]))


def test_lockstep_labels_start_a_shortest_path_and_are_the_first_such_in_the_order():
    teacher = Teacher(SMALL, slack=200, order="lockstep")
    checked = 0
    for scenario in scenarios(SMALL, range(20)):
        path = shortest_path(scenario, config=SMALL)
        if path is None:
            continue
        label = teacher.label(scenario)
        assert steps_after(SMALL, scenario, label) == len(path) - 1
        order = order_at(scenario)
        earlier = order[: order.index(label)]
        assert all(steps_after(SMALL, scenario, joint) != len(path) - 1 for joint in earlier)
        checked += 1
    assert checked >= 15


def test_widest_labels_start_the_most_shortest_paths_lockstep_first_ties_by_the_order():
    teacher = Teacher(SMALL, slack=200, order="widest")
    checked = 0
    for scenario in scenarios(SMALL, range(20)):
        found = shortest_path_counts(scenario, config=SMALL)
        if found is None:
            assert teacher.label(scenario) is None
            continue
        label, counts = teacher.label(scenario), found[1]
        assert steps_after(SMALL, scenario, label) == found[0] - 1
        order = order_at(scenario)
        lockstep = {joint: n for joint, n in counts.items() if joint[0] == joint[1]}
        among = lockstep or counts
        assert label in among and counts[label] == max(among.values())
        assert all(among.get(joint, 0) < counts[label] for joint in order[: order.index(label)])
        checked += 1
    assert checked >= 15


@pytest.mark.parametrize("setting", [1, 2])
def test_tolerant_formation_labels_leave_room_for_a_slip_when_a_shortest_path_allows(setting):
    """After a tolerant label (played with the game's own step) the formation would survive any one
    agent one cell off, whenever a joint action that starts a shortest path allows that; the label
    still starts a shortest path, and the spec's starts (2 cells apart in a line) get new labels."""
    config = GameConfig.from_setting(setting, height=11, width=11, n_obstacles=2, max_steps=30)
    teacher = Teacher(config, slack=200, order="lockstep", tolerant_formation=True)
    plain = Teacher(config, slack=200, order="lockstep")

    def roomy(scenario, joint) -> bool:
        game = BatchedGame(config, batch_size=1)
        game.load([scenario])
        game.step(np.array([joint]))
        leader, follower = (tuple(int(x) for x in cell) for cell in game.positions[0])
        offsets = [(0, 0), (-1, 0), (1, 0), (0, -1), (0, 1)]
        return all(config.formation_kept(math.dist((leader[0] + a, leader[1] + b), (follower[0] + c, follower[1] + d)))
                   for a, b in offsets for c, d in offsets if (a, b) == (0, 0) or (c, d) == (0, 0))

    differs = 0
    for scenario in scenarios(config, range(25)):
        found = shortest_first_moves(scenario, config=config)
        if found is None:
            continue
        label = teacher.label(scenario)
        assert label in found[1]
        assert roomy(scenario, label) == any(roomy(scenario, joint) for joint in found[1])
        differs += label != plain.label(scenario)
    assert differs >= 10


def test_robust_first_step_label_is_the_same_whatever_the_hidden_velocities():
    teacher = Teacher(SMALL, slack=6, order="lockstep", robust_first_step=True)
    speeds = [1, -1, 2, -2]
    distinct = set()
    for scenario in scenarios(SMALL, range(8)):
        labels = set()
        for v in speeds:
            seen_the_same = scenario.__class__(scenario.leader, scenario.followers,
                                               tuple((r, c, v) for r, c, _ in scenario.obstacles))
            labels.add(teacher.label(seen_the_same, first_step=True))
        assert len(labels) == 1, labels
        distinct |= labels
        # after the first step the teacher is clairvoyant again
        assert teacher.label(scenario) == Teacher(SMALL, slack=6, order="lockstep").label(scenario)
    assert None not in distinct


def test_robust_label_keeps_a_path_for_at_least_as_many_velocities_as_any_other_action():
    teacher = Teacher(SMALL, slack=6, order="lockstep", robust_first_step=True)
    speeds = [1, -1, 2, -2]
    for scenario in scenarios(SMALL, range(5)):
        variants = [scenario.__class__(scenario.leader, scenario.followers,
                                       tuple((r, c, v) for r, c, _ in scenario.obstacles)) for v in speeds]

        kept = {joint: sum(teacher._opens(variant, joint) for variant in variants)
                for joint in itertools.product(range(4), repeat=2)}
        assert kept[teacher.label(scenario, first_step=True)] == max(kept.values())


def test_safe_labels_keep_a_path_and_bring_the_leader_closer_when_they_can():
    slack = 6
    teacher = Teacher(SMALL, slack=slack, order="safe")
    dest_row, dest_col = SMALL.destination

    def to_go(cell):
        return max(cell[0] - dest_row, abs(cell[1] - dest_col))

    checked = 0
    for scenario in scenarios(SMALL, range(20)):
        label = teacher.label(scenario)
        if label is None:
            assert shortest_path(scenario, config=SMALL.replace(max_steps=to_go(scenario.leader) + slack)) is None
            continue
        assert teacher._opens(scenario, label)
        game = BatchedGame(SMALL, batch_size=1)
        game.load([scenario])
        game.step(np.array([label]))
        closer = to_go(tuple(game.positions[0, 0])) < to_go(scenario.leader)
        if not closer:  # then no move that brings the leader closer keeps a path
            order = lockstep_order(2, 2 if scenario.leader[1] < dest_col else 1)
            for joint in order:
                probe = BatchedGame(SMALL, batch_size=1)
                probe.load([scenario])
                probe.step(np.array([joint]))
                if to_go(tuple(probe.positions[0, 0])) < to_go(scenario.leader):
                    assert not teacher._opens(scenario, joint)
        checked += 1
    assert checked >= 15


def test_following_safe_labels_succeeds():
    teacher = Teacher(SMALL, slack=6, order="safe", robust_first_step=True)
    game = BatchedGame(SMALL, batch_size=1)
    wins = 0
    for seed in range(20):
        game.reset(seed=seed)
        while not game.done[0]:
            label = teacher.label(game.scenario(0), first_step=game.steps[0] == 0)
            game.step(np.array([label if label is not None else (3, 3)]))
        wins += bool(game.success[0])
    assert wins >= 18


def test_response_labels_answer_the_leaders_own_move_with_a_shortest_path_when_one_exists():
    teacher = Teacher(SMALL, slack=200, order="lockstep")
    answered = kept = 0
    for scenario, joint, best in labelled_states(teacher, 60):
        assert teacher.respond(scenario, joint, joint[0]) == joint  # the teacher's own leader move: its label
        for leader_move in set(range(4)) - {joint[0]}:
            response = teacher.respond(scenario, joint, leader_move)
            assert response[0] == joint[0]  # the leader keeps the teacher's label
            with_follower = [(leader_move, f) for f in range(4)]
            shortest = [j for j in with_follower if steps_after(SMALL, scenario, j) == best]
            if not shortest:  # no follower move makes the leader's move a shortest path: the teacher's label
                assert response == joint
                kept += 1
                continue
            # the first in the lockstep order of the follower moves that keep a shortest path
            assert (leader_move, response[1]) == next(j for j in order_at(scenario) if j in shortest)
            answered += 1
    assert answered > 20 and kept > 20
    # the first screen, with robust labels, keeps the teacher's label
    robust = Teacher(SMALL, slack=200, order="lockstep", robust_first_step=True)
    scenario = scenarios(SMALL, [3])[0]
    joint = robust.label(scenario, first_step=True)
    assert robust.respond(scenario, joint, (joint[0] + 1) % 4, first_step=True) == joint


@pytest.mark.parametrize("follower_labels", ["teacher", "response"])
def test_rollout_actor_learns_from_response_labels_but_demonstrations_play_the_teachers(follower_labels, rollout_actor):
    actor = rollout_actor({"train.follower_labels": follower_labels,
                                                "train.follower_answers_leader": False})
    game, teacher = actor.rollout.game, actor._teacher
    scenarios = [game.scenario(i) for i in range(game.batch_size)]
    first = [teacher.label(s, first_step=True) for s in scenarios]
    # a leader that never makes the teacher's move, on a later step (robust first-step labels stay)
    game.steps[:] = 1
    greedy = np.array([[((j[0] if j else 0) + 1) % 4, 0] for j in first])
    joints = actor._teacher_joints()
    labels, _ = actor._labels(joints, greedy, greedy)
    changed = 0
    for i, scenario in enumerate(scenarios):
        joint = teacher.label(scenario)
        assert tuple(joints[i]) == joint
        expected = joint if follower_labels == "teacher" else teacher.respond(scenario, joint, int(greedy[i, 0]))
        assert tuple(labels[i]) == expected and labels[i, 0] == joint[0]
        changed += tuple(labels[i]) != joint
    assert (changed > 0) == (follower_labels == "response")


def test_answers_to_the_leaders_move_start_a_shortest_path_else_survive_the_step():
    teacher = Teacher(SMALL, slack=200, order="lockstep")
    shortest_answers = surviving_answers = none = 0
    for scenario, joint, best in labelled_states(teacher, 40):
        assert teacher.answer(scenario, joint, joint[0]) == joint  # the label's own leader move: the label
        for leader_move in set(range(4)) - {joint[0]}:
            answer = teacher.answer(scenario, joint, leader_move)
            with_leader = [j for j in order_at(scenario) if j[0] == leader_move]
            after = {j: steps_after(SMALL, scenario, j) for j in with_leader}
            shortest = [j for j in with_leader if after[j] == best]
            if shortest:  # the first, in the lockstep order, that keeps a shortest path
                assert answer == shortest[0]
                shortest_answers += 1
                continue
            surviving = [j for j in with_leader if not ended(scenario, j)]
            if surviving:  # else the first after which the team still plays
                assert answer == surviving[0]
                surviving_answers += 1
            else:
                assert answer is None
                none += 1
    assert shortest_answers > 20 and surviving_answers > 20


def ended(scenario, joint) -> bool:
    """Whether ``joint`` ends the game in ``scenario`` without winning it."""
    game = BatchedGame(SMALL, batch_size=1)
    game.load([scenario])
    game.step(np.array([joint]))
    return bool(game.done[0] and not game.success[0])


def test_followers_that_answer_the_leader_play_and_learn_the_answer_to_the_move_it_plays(rollout_actor):
    actor = rollout_actor({"train.follower_answers_leader": True, "train.epsilon_start": 0.5,
                                                "train.epsilon_end": 0.5})
    game, teacher = actor.rollout.game, actor._teacher
    obs = actor.rollout.observations
    greedy, actions = actor._actions(obs)
    with torch.no_grad():
        leader_q = actor.module["leader"].q_network(torch.from_numpy(obs)).numpy()
        follower_q = actor.module["follower"].q_network(torch.from_numpy(obs)).numpy().reshape(-1, 4, 4)
    assert follower_q.shape[0] == len(obs)
    assert (greedy[:, 0] == leader_q.argmax(1)).all()
    rows = np.arange(len(obs))
    assert (greedy[:, 1] == follower_q[rows, greedy[:, 0]].argmax(1)).all()  # the answer to the greedy move
    assert (actions[:, 1] == follower_q[rows, actions[:, 0]].argmax(1)).all()  # and to the move played
    assert (actions[:, 0] != greedy[:, 0]).any()  # the leader explored somewhere (epsilon 0.5)
    # labels: the teacher's answer to the move the leader plays
    game.steps[:] = 1
    joints = actor._teacher_joints()
    played = np.array([[((j[0] + 1) % 4) if j[0] >= 0 else 0, 0] for j in joints])
    labels, answers = actor._labels(joints, greedy, played)
    assert answers is None  # train.answer_every_leader_move is off
    for i in range(game.batch_size):
        joint = teacher.label(game.scenario(i))
        if joint is None:
            assert (labels[i] == -1).all()
            continue
        answer = teacher.answer(game.scenario(i), joint, int(played[i, 0]))
        assert labels[i, 0] == joint[0]  # the leader learns the teacher's move
        assert labels[i, 1] == (answer[1] if answer is not None else -1)


def test_with_answer_every_leader_move_a_follower_learns_its_answer_to_each_move_the_leader_could_make(rollout_actor):
    actor = rollout_actor({"train.follower_answers_leader": True,
                                                "train.answer_every_leader_move": True})
    game, teacher = actor.rollout.game, actor._teacher
    game.steps[:] = 1
    joints = actor._teacher_joints()
    played = np.array([[((j[0] + 1) % 4) if j[0] >= 0 else 0, 0] for j in joints])
    labels, answers = actor._labels(joints, greedy=played, actions=played)
    assert answers.shape == (game.batch_size, 2, 4)
    assert (answers[:, 0] == -1).all()  # the leader has no answers to learn
    taught = none = 0
    for i in range(game.batch_size):
        joint = teacher.label(game.scenario(i))
        if joint is None:
            assert (labels[i] == -1).all() and (answers[i] == -1).all()
            continue
        for move in range(4):
            answer = teacher.answer(game.scenario(i), joint, move)
            assert answers[i, 1, move] == (answer[1] if answer is not None else -1)
            taught += answer is not None
            none += answer is None
        assert answers[i, 1, joint[0]] == joint[1]  # the label's own leader move: the label
        assert labels[i, 0] == joint[0] and labels[i, 1] == answers[i, 1, played[i, 0]]  # the move played
    assert taught > 2 * game.batch_size  # most rows are taught, not only the played one
    chunk = actor.rollout.step(played, labels=labels, answers=answers)
    assert (chunk.answers[: game.batch_size] == answers).all()


def test_labels_of_a_batch_are_each_states_own_label_and_robust_first_steps_keep_the_most_paths():
    """``Teacher.labels`` searches a batch of states at once (the rollout actors' way) and a first
    step's hypotheses of the obstacles' velocities at once: on setting 1 (two obstacles' velocities
    unknown, 16 hypotheses) each label is what a state labelled alone gets, and a first step's label
    keeps a path open for as many hypotheses as any joint action (counted one hypothesis at a time)."""
    config = GameConfig.from_setting(1)
    starts = scenarios(config, range(4))
    later = []
    for scenario in starts:
        game = BatchedGame(config, 1)
        game.load([scenario])
        for joint in (shortest_path(scenario, config=config) or [])[:6]:
            game.step(np.array([joint]))
            later.append(game.scenario(0))
    batch, firsts = starts + later, [True] * len(starts) + [False] * len(later)
    labels = Teacher(config, slack=6, order="lockstep", robust_first_step=True).labels(batch, firsts)
    alone = Teacher(config, slack=6, order="lockstep", robust_first_step=True)
    assert labels == [alone.label(s, first_step=f) for s, f in zip(batch, firsts)]
    assert len(set(labels)) > 1 and None not in labels[:len(starts)]
    for scenario, label in list(zip(starts, labels))[:2]:
        near = alone._nearest_obstacles(scenario)
        hypotheses = []
        for velocities in itertools.product([1, -1, 2, -2], repeat=2):
            obstacles = list(scenario.obstacles)
            for i, v in zip(near, velocities):
                obstacles[i] = (*obstacles[i][:2], v)
            hypotheses.append(scenario.__class__(scenario.leader, scenario.followers, tuple(obstacles)))
        kept = {joint: sum(alone._opens(h, joint) for h in hypotheses)
                for joint in itertools.product(range(4), repeat=2)}
        assert kept[label] == max(kept.values()) and min(kept.values()) < max(kept.values())


def test_accepted_joint_actions_are_those_that_start_a_shortest_path_and_hold_the_label():
    teacher = Teacher(SMALL, slack=200, order="lockstep", robust_first_step=True)
    several = narrower = 0
    for scenario, joint, best in labelled_states(teacher, 40):
        mask = teacher.accepted(scenario, joint)
        accepted = {(m // 4, m % 4) for m in range(16) if mask >> m & 1}
        assert joint in accepted
        # every accepted joint action leaves a path as short as the label's, and no other does
        for other in itertools.product(range(4), repeat=2):
            assert (other in accepted) == (steps_after(SMALL, scenario, other) == best), (scenario, other)
        several += len(accepted) > 1
        # "toward": of those, the label and the ones whose leader move keeps or closes the gap to the
        # destination's column
        toward_mask = teacher.accepted(scenario, joint, toward=True)
        gap = abs(scenario.leader[1] - SMALL.destination[1])
        for m in range(16):
            leader_col = min(max(scenario.leader[1] + int(MOVES[m // 4, 1]), 0), SMALL.width - 1)
            kept = mask >> m & 1 and (abs(leader_col - SMALL.destination[1]) <= gap or (m // 4, m % 4) == joint)
            assert (toward_mask >> m & 1) == kept
        narrower += toward_mask != mask
        # on a first step the robust label stands alone: the screens do not show the motion yet
        first = teacher.label(scenario, first_step=True)
        assert teacher.accepted(scenario, first, first_step=True) == 1 << (4 * first[0] + first[1])
    assert several > 10 and narrower > 3
    with pytest.raises(ValueError, match="one follower"):
        Teacher(GameConfig.from_setting(None, height=9, width=9, n_obstacles=1, n_followers=2), slack=6,
                order="lockstep").accepted(scenarios(SMALL, [0])[0], (0, 0, 0))


@pytest.mark.parametrize("which", ["team", "toward"])
def test_rollout_actor_stores_the_accepted_joint_actions_of_each_labelled_state(which, rollout_actor):
    actor = rollout_actor({"train.follower_answers_leader": True,
                                                "train.any_shortest_move": which})
    game, teacher = actor.rollout.game, actor._teacher
    game.steps[:] = 1
    joints = actor._teacher_joints()
    accepted = actor._accepted(joints)
    for i in range(game.batch_size):
        if joints[i, 0] < 0:
            assert accepted[i] == 0
        else:
            assert accepted[i] == teacher.accepted(game.scenario(i), tuple(int(a) for a in joints[i]),
                                                   toward=which == "toward")
    assert (joints[:, 0] >= 0).any()
    chunk = actor.rollout.step(joints.clip(min=0), labels=joints, accepted=accepted)
    assert (chunk.accepted[: game.batch_size] == accepted).all()
