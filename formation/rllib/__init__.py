"""The recipe (``formation.recipe``) on Ray RLlib: the algorithm and its config (``algorithm``), the learner that
calls the recipe's loss (``learner``), the RLModule (``module``), and the replay and rollout actors
(``replay_actor``, ``rollout_actor``). Nothing below this layer imports it."""
