"""Task definitions (one TOML file per task); shipped inside the package as `rvt2cli._tasks`."""
