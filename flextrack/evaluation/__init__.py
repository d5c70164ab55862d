"""Evaluations of the estimators' outputs beyond their pose error (`flextrack evaluate ...`)."""
