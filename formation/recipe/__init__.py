"""The recipe, free of Ray: the run's config (``config``), the networks (``qnet``), the team's modules and
spaces (``team``), DAgger's teacher (``teacher``), reward shaping (``shaping``), batches of games played into
replay records (``rollout``), the numpy replay (``replay``), the learning step (``loss``) and the safety heads'
refit (``safety_refit``). ``formation.rllib`` runs it on Ray RLlib; ``formation.policy`` plays what it trained
with torch alone."""
