"""Statistics: the paper's error metrics, the chi-square distribution, moved markers."""
