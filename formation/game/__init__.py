"""The game itself: rules (``core``), scenarios, and what the agents see (``render``).

Nothing here knows of Ray, torch or PettingZoo.
"""

from formation.game.core import ACTION_NAMES, COLLISION_OFFSETS, MOVES, BatchedGame
from formation.game.render import FrameStack, GridRenderer, Observer, ScreenRenderer
from formation.game.scenario import Scenario, parse_scenario

__all__ = ["ACTION_NAMES", "COLLISION_OFFSETS", "MOVES", "BatchedGame", "FrameStack", "GridRenderer", "Observer",
           "Scenario", "ScreenRenderer", "parse_scenario"]
