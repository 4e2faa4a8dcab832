"""Builders shared by test modules in several folders (not tests themselves). ``tests/`` is on
``sys.path`` through ``pythonpath`` in pyproject.toml's ``[tool.pytest.ini_options]``, so every
test module imports them as ``support.<module>``."""
