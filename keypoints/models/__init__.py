"""Built-in model descriptions (TOML package data)."""
