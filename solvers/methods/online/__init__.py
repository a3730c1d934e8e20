"""Online estimators: recursive least squares with forgetting, MRAS."""
