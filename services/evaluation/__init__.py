"""Truth and scoring: metrics (pure numpy), reports, and the live evaluator (the baselines are in :mod:`services.baselines`)."""
