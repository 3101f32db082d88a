"""Helpers shared by test modules in several folders (fakes, readers, settings, paths): not tests themselves.
Imported as `support.<module>`; pytest puts tests/ on sys.path (pyproject.toml: `pythonpath = ["tests"]`)."""
