"""Leader/follower teams that keep formation through moving obstacles, trained with multi-agent DQN on Ray RLlib.

``formation.policy.load`` plays a trained team with torch alone; the ``formation`` command trains,
evaluates, exports and draws (``formation --help``)."""

# as pyproject.toml says (tests/test_cli.py); `formation --version` asks the installed one first
__version__ = "0.4.0.dev0"
