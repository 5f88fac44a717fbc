"""Batch work over the frames of a data set, in this process or on a Ray cluster: one job
(``jobs``) per command, one runner (``runner.run_frames``) for both paths."""
