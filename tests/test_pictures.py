"""`formation render`: the paper's pictures of a trained policy (episodes.gif, paths.png, q_values.png,
training.png). One smoke run (conftest's ``smoke_run``) serves the whole module."""

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from formation import pictures
from formation.cli import main
from formation.policy import load

EPISODES = 3


@pytest.fixture(scope="module")
def run_dir(smoke_run) -> Path:
    return smoke_run


def not_flat(image: Image.Image) -> bool:
    pixels = np.asarray(image.convert("RGB")).reshape(-1, 3)
    return len(np.unique(pixels, axis=0)) > 2


def test_render_writes_the_four_pictures_at_their_sizes(run_dir, tmp_path, capsys):
    out = tmp_path / "pictures"
    assert main(["render", str(run_dir), "--out", str(out), "--episodes", str(EPISODES), "--seed", "7"]) == 0
    printed = capsys.readouterr().out
    game = load(run_dir).game
    expected = {"episodes.gif": pictures.episodes_gif_size(EPISODES),
                "paths.png": pictures.paths_size(game, EPISODES),
                "q_values.png": pictures.q_values_size(1 + game.n_followers),
                "training.png": pictures.training_size()}
    for name, size in expected.items():
        path = out / name
        assert path.is_file() and path.stat().st_size > 0, name
        assert f"wrote {path}" in printed
        with Image.open(path) as image:
            assert image.size == size, name
            assert not_flat(image), name
            if name == "episodes.gif":
                assert image.n_frames > 1
                image.seek(image.n_frames - 1)
                assert not_flat(image)
    # the layout constants give the sizes: three enlarged 84-pixel screens side by side
    assert pictures.episodes_gif_size(EPISODES)[0] == EPISODES * 84 * pictures.SCALE + (EPISODES - 1) * pictures.GAP


def test_paths_follow_the_replayed_episode_and_draw_the_leaders_start(run_dir):
    policy = load(run_dir)
    game = policy.game
    episodes = pictures.play_episodes(policy, 2, seed=11)
    for e in episodes:
        assert len(e.leader) == e.steps + 1 == len(e.screens) and len(e.q) == e.steps >= 1
        assert e.leader[0] == tuple(game.starts[0]) and e.followers[0][0] == tuple(game.starts[1][0])
        # greedy actions are the argmax of the recorded Q-values, as policy.act_batch chooses them
        assert all(np.array_equal(np.argmax(q, axis=1), a) for q, a in zip(e.q, e.actions))
        # the leader moves by the actions' moves (clamped to the board)
        r, c = e.leader[0]
        dr, dc = {0: (-1, 0), 1: (-1, -1), 2: (-1, 1), 3: (0, 0)}[int(e.actions[0][0])]
        assert e.leader[1] == (max(0, min(game.height - 1, r + dr)), max(0, min(game.width - 1, c + dc)))
        image, centre = pictures.draw_paths(game, e)
        assert image.size == pictures.paths_panel_size(game)
        pixels = np.asarray(image)
        x, y = centre(e.leader[0])
        assert tuple(pixels[y, x]) == pictures.LEADER
        x, y = centre(e.followers[0][0])
        assert tuple(pixels[y, x]) == pictures.FOLLOWER
        dest = centre(game.destination)
        assert tuple(pixels[dest[1], dest[0]]) in (pictures.DESTINATION, pictures.LEADER)
        # a cell no one ever visits stays board-black at its centre
        visited = {*e.leader, *(p for f in e.followers for p in f), *(p for o in e.obstacles for p in o),
                   game.destination}
        free = [(r, c) for r in range(game.height) for c in range(game.width) if (r, c) not in visited
                and all(abs(r - vr) + abs(c - vc) > 1 for vr, vc in visited)]
        for cell in free[:5]:
            x, y = centre(cell)
            assert tuple(pixels[y, x]) == pictures.BOARD
    # the key frames of the Q-value figure are steps of the episode, the first one first
    steps = pictures.key_steps(episodes[0])
    assert len(steps) == pictures.KEY_FRAMES and steps[0] == 0 and max(steps) == episodes[0].steps - 1


def test_export_renders_without_training_curves(run_dir, tmp_path, cli):
    export_dir = tmp_path / "export"
    assert main(["export", str(run_dir), str(export_dir)]) == 0
    out = tmp_path / "pictures"
    done = cli("render", str(export_dir), "--out", str(out), "--episodes", "1")
    assert done.returncode == 0, done.stderr[-3000:]
    assert sorted(p.name for p in out.iterdir()) == ["episodes.gif", "paths.png", "q_values.png"]
    assert "training.png: skipped" in done.stdout
    with Image.open(out / "paths.png") as image:
        assert image.size == pictures.paths_size(load(export_dir).game, 1)


def test_training_curves_skip_unreadable_values(tmp_path):
    metrics = tmp_path / "run" / "metrics.jsonl"
    metrics.parent.mkdir()
    metrics.write_text('{"env_steps": 0, "explore/success": NaN}\n'
                       '{"env_steps": 100, "explore/success": 0.5, "explore/return_leader": 3.0}\n'
                       'not json\n'
                       '{"env_steps": 200, "greedy/success": 0.25, "greedy/return_mean/leader": 4.0, '
                       '"greedy/return_mean/follower": -1.0}\n')
    success, returns = pictures.training_series(pictures.read_metrics(metrics))
    assert [(s[0], s[2], s[3]) for s in success] == [("explore", [100.0], [0.5]), ("greedy", [200.0], [0.25])]
    assert [s[0] for s in returns] == ["leader (explore)", "leader (greedy)", "follower (greedy)"]
    path = pictures.write_training(tmp_path / "training.png", metrics)
    with Image.open(path) as image:
        assert image.size == pictures.training_size() and not_flat(image)
    assert pictures.nice_ticks(0, 1) == [0.0, 0.2, 0.4, 0.6, 0.8, 1.0]


@pytest.mark.parametrize("args", [["render", "no/such/run", "--out", "x"], ["render", "configs", "--out", "x"],
                                  ["render", "configs", "--out", "x", "--episodes", "0"]])
def test_bad_input_is_one_line_and_a_failure(args, tmp_path, capsys):
    args = [a if a != "x" else str(tmp_path / "x") for a in args]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("formation: error:") and "\n" not in err
    assert not (tmp_path / "x").exists()


def test_render_draws_another_game_the_policy_plays(run_dir, tmp_path, capfd):
    out = tmp_path / "setting2"
    assert main(["render", str(run_dir), "--out", str(out), "--episodes", "1", "--setting", "2"]) == 0
    game = load(run_dir).for_game(setting=2).game
    with Image.open(out / "paths.png") as image:  # drawn on setting 2's 25x25 board, not the 9x9 one trained on
        assert image.size == pictures.paths_size(game, 1) != pictures.paths_size(load(run_dir).game, 1)
    capfd.readouterr()
    assert main(["render", str(run_dir), "--out", str(out), "--followers", "2"]) != 0
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--followers: " in err[0] and "plays 1 to 1" in err[0]
    assert main(["render", str(run_dir), "--out", str(out), "--set", "n_obstacles=99"]) != 0
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--set n_obstacles: 99 is not allowed" in err[0]
