"""The recipe (``formation.recipe``) on Ray RLlib: the algorithm and its config (``algorithm``), the learner that
calls the recipe's loss (``learner``), the RLModule (``module``), the replay and rollout actors (``replay_actor``,
``rollout_actor``), and the game as an RLlib ``MultiAgentEnv`` (``env``, for RLlib's own algorithms). Nothing below
this layer imports it."""
