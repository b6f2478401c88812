"""DAgger's teacher: labels start shortest paths, follow the lockstep order, and do not depend on
what the first screen cannot show."""

import itertools

import numpy as np
import pytest
import torch

from formation import planner
from formation.config import GameConfig
from formation.game import BatchedGame
from formation.planner import shortest_path
from formation.recipe.rollout import GameRollout
from formation.recipe.teacher import Teacher, lockstep_order, safety_labels

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


def test_lockstep_labels_start_a_shortest_path_and_are_the_first_such_in_the_order():
    teacher = Teacher(SMALL, slack=200)
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


def test_robust_first_step_label_is_the_same_whatever_the_hidden_velocities():
    teacher = Teacher(SMALL, slack=6, robust_first_step=True)
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
        assert teacher.label(scenario) == Teacher(SMALL, slack=6).label(scenario)
    assert None not in distinct


def test_robust_label_keeps_a_path_for_at_least_as_many_velocities_as_any_other_action():
    teacher = Teacher(SMALL, slack=6, robust_first_step=True)
    speeds = [1, -1, 2, -2]
    for scenario in scenarios(SMALL, range(5)):
        variants = [scenario.__class__(scenario.leader, scenario.followers,
                                       tuple((r, c, v) for r, c, _ in scenario.obstacles)) for v in speeds]

        kept = {joint: sum(teacher._opens(variant, joint) for variant in variants)
                for joint in itertools.product(range(4), repeat=2)}
        assert kept[teacher.label(scenario, first_step=True)] == max(kept.values())


def test_answers_to_the_leaders_move_start_a_shortest_path_else_survive_the_step():
    teacher = Teacher(SMALL, slack=200)
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


def test_followers_that_answer_the_leader_play_and_learn_the_answer_to_the_move_it_plays(collector):
    actor, networks = collector({"train.follower_answers_leader": True, "train.epsilon_start": 0.5,
                                 "train.epsilon_end": 0.5, "teacher.margin": 5.0})
    game, teacher = actor.rollout.game, actor.teacher
    obs = actor.rollout.observations
    actions = actor.actions(networks, env_steps=0)
    with torch.no_grad():
        leader_q = networks["leader"](torch.from_numpy(obs)).numpy()
        follower_q = networks["follower"](torch.from_numpy(obs)).numpy().reshape(-1, 4, 4)
    assert follower_q.shape[0] == len(obs)
    rows = np.arange(len(obs))
    assert (actions[:, 1] == follower_q[rows, actions[:, 0]].argmax(1)).all()  # the answer to the move played
    assert (actions[:, 0] != leader_q.argmax(1)).any()  # the leader explored somewhere (epsilon 0.5)
    # labels: the teacher's answer to the move the leader plays
    game.steps[:] = 1
    joints = actor._teacher_joints()
    played = np.array([[((j[0] + 1) % 4) if j[0] >= 0 else 0, 0] for j in joints])
    labels, answers = actor._labels(joints, played)
    assert answers is None  # teacher.answer_every_leader_move is off
    for i in range(game.batch_size):
        joint = teacher.label(game.scenario(i))
        if joint is None:
            assert (labels[i] == -1).all()
            continue
        answer = teacher.answer(game.scenario(i), joint, int(played[i, 0]))
        assert labels[i, 0] == joint[0]  # the leader learns the teacher's move
        assert labels[i, 1] == (answer[1] if answer is not None else -1)


def test_with_answer_every_leader_move_a_follower_learns_its_answer_to_each_move_the_leader_could_make(collector):
    actor, _ = collector({"train.follower_answers_leader": True, "teacher.answer_every_leader_move": True})
    game, teacher = actor.rollout.game, actor.teacher
    game.steps[:] = 1
    joints = actor._teacher_joints()
    played = np.array([[((j[0] + 1) % 4) if j[0] >= 0 else 0, 0] for j in joints])
    labels, answers = actor._labels(joints, played)
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
    labels = Teacher(config, slack=6, robust_first_step=True).labels(batch, firsts)
    alone = Teacher(config, slack=6, robust_first_step=True)
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


def rollout_calls(teacher, config, steps):
    """What a rollout actor asks the teacher at every step of a ``steps`` long rollout of 8 games (labels, answers to
    every leader move, safety labels), in its order; and the states and first steps asked
    about, per step. Half the games play the labels, the others the label's or a random leader move (30%) and
    the answer to it or a random joint move (30%), so the states include first steps and states off the shortest
    paths."""
    rollout, rng = GameRollout(config, 8, seed=1), np.random.default_rng(1)
    game, asked, told = rollout.game, [], []
    for _ in range(steps):
        states, firsts = [game.scenario(i) for i in range(8)], list(game.steps == 0)
        told.append(teacher_outputs(teacher, config, states, firsts))
        asked.append((states, firsts))
        actions = rng.integers(0, 4, (8, 2))
        for i, (joint, answers) in enumerate(zip(*told[-1][:2])):
            if joint is None:
                continue
            leader = int(rng.integers(4)) if i >= 4 and rng.random() < 0.3 else joint[0]
            if answers[leader] is not None and (i < 4 or rng.random() >= 0.3):
                actions[i] = answers[leader]
            actions[i, 0] = leader
        rollout.step(actions)
    return told, asked


def teacher_outputs(teacher, config, states, firsts):
    joints = teacher.labels(states, firsts)
    answers = [teacher.answers(s, j) if j is not None else None for s, j in zip(states, joints)]
    return joints, answers, safety_labels(states, config, 4).tolist()


@pytest.mark.parametrize("setting", [1, 2])
def test_the_teacher_tells_a_rollout_what_searches_of_each_state_alone_tell(setting, monkeypatch):
    """Along epsilon-greedy rollouts, the teacher's labels, answers and safety labels are those
    of a reference teacher that searches every state afresh (nothing kept from the searches of earlier states of
    an episode) with layers of cells (no move table) and full searches only (no beam), and plays a step in the game
    to see whether a joint action survives it."""
    config = GameConfig.from_setting(setting)
    told, asked = rollout_calls(Teacher(config, slack=6, robust_first_step=True), config, 25)
    monkeypatch.setattr(planner, "MOVE_TABLE_LIMIT", 0)
    monkeypatch.setattr(planner, "_beam_exists", lambda board, zones, starts, *_: np.zeros(len(starts), bool))
    reference = Teacher(config, slack=6, robust_first_step=True)
    reference._ahead = reference._surviving = None
    assert [teacher_outputs(reference, config, states, firsts) for states, firsts in asked] == told
    firsts = sum(f for _, fs in asked for f in fs)
    assert 8 < firsts < 100 and any(j is None for step in told for j in step[0])


def test_a_full_cache_keeps_every_state_of_the_batch_it_searches():
    """The teacher keeps the searches of its last 256 states; a batch that brings new states must not drop the
    states of that same batch found before (a rollout asked for one and met a KeyError)."""
    teacher = Teacher(SMALL, slack=6)
    game = BatchedGame(SMALL, batch_size=3, seed=5)
    game.reset()
    kept, *new = [game.scenario(i) for i in range(3)]
    teacher._find_starts([kept])  # the oldest entry of a full cache ...
    teacher._found.update({("older", i): None for i in range(255)})
    assert len(teacher._found) == 256 and next(iter(teacher._found)) == kept
    teacher._find_starts([kept, *new])  # ... asked for again beside new states
    assert all(s in teacher._found for s in [kept, *new]) and len(teacher._found) == 256
