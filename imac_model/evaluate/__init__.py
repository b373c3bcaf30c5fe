"""Evaluation building blocks of the world model (issue 17)."""
