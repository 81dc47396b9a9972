"""Small per-model training configurations (TOML)."""
