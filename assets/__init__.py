"""Data files, installed as ``methd_jax.assets``: the base's MJCF, the lab twin, the sample user
trajectories and deployment bag, and the shipped policies (``pretrained/``). See README.md here."""
