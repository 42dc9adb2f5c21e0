"""Floor 2, the presets: the loader and the shipped preset YAMLs."""
