"""The four baselines and their training: the engine at this level (config, data, train, run folder,
checkpoints, validation, evaluation, floor), the shared network parts in layers/, the families in models/."""
