"""Dataset adapters: each turns one raw dataset layout into `pipeline.records.Log` records.

They import their devkit (av2, nuscenes-devkit) lazily: those imports cost seconds.
"""
