"""Running the detector: the command line, the training loop and its settings, evaluation with
the official metric, checkpoints, the robustness suite and the pictures."""
