"""Scene files shipped with sonarsim (TOML; see docs/scenes.md). Data only."""
