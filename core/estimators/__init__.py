"""Estimators: Lötters (offsets / 6), starting points, held-out evaluation."""
