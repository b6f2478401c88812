"""Imports point one way: the Ray-free layers (the game, the PettingZoo view, the planner, the recipe, the policy,
the shield, evaluation and pictures) import nothing of the RLlib layer (``formation.rllib``) or of Ray, so that
loading and playing a policy needs torch alone."""

import ast
import subprocess
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "formation"
RAY_FREE = ["formation.policy", "formation.evaluate", "formation.pictures", "formation.shield", "formation.planner",
            "formation.config", "formation.env", "formation.env.pettingzoo", "formation.game",
            *sorted(f"formation.recipe.{p.stem}" for p in (PACKAGE / "recipe").glob("*.py") if p.stem != "__init__")]


def ray_free_files() -> list[Path]:
    files = [*(PACKAGE / "game").glob("*.py"), *(PACKAGE / "recipe").glob("*.py"), PACKAGE / "env" / "__init__.py",
             PACKAGE / "env" / "pettingzoo.py"]
    return sorted(files + [PACKAGE / f"{name}.py" for name in ("policy", "evaluate", "pictures", "shield",
                                                                 "planner", "config")])


def test_importing_the_ray_free_layers_and_loading_a_policy_does_not_import_ray():
    code = (f"import {', '.join(RAY_FREE)}; import sys\n"
            "from formation.policy import load; load('policies/setting1')\n"
            "bad = sorted(m for m in sys.modules if m == 'ray' or m.startswith(('ray.', 'formation.rllib')))\n"
            "assert not bad, bad")
    done = subprocess.run([sys.executable, "-c", code], cwd=PACKAGE.parent, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]


def test_no_ray_free_module_names_ray_or_the_rllib_layer_in_an_import():
    found = []
    for path in ray_free_files():
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            found += [f"{path.relative_to(PACKAGE.parent)}:{node.lineno} {name}" for name in names
                      if name == "ray" or name.startswith(("ray.", "formation.rllib", "formation.train",
                                                           "formation.cli"))]
    assert not found, found


def test_nothing_refers_to_the_old_learn_package():
    root = PACKAGE.parent
    hits = [str(p.relative_to(root)) for folder in ("formation", "tests", "benchmarks", "experiments")
            for p in (root / folder).rglob("*.py") if "formation.learn" in p.read_text() and p != Path(__file__)]
    assert not hits, hits
