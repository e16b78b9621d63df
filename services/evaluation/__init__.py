"""Truth and scoring: metrics (pure numpy), the dead-reckoning baseline, reports, and the live evaluator."""
