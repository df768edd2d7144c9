"""Offline reprocessing of a recorded session: stages chained by a short pipeline."""
