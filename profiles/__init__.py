"""The bundled device profiles (YAML); this file only makes them an installable package."""
