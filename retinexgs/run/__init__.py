"""A trained run: its folder (config.yaml, checkpoints, the scene it reads), the model rebuilt from it, and how
it renders.

``retinexgs.train`` writes runs; ``evaluate``, ``export``, ``view`` and ``bench`` read them through this
package and import nothing from ``train`` (the layers are checked by import-linter, see ``.importlinter``).
"""
