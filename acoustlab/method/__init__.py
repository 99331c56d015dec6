"""The localization method: the pipeline in typed steps, the trust check, training-row capping, the protocols."""
