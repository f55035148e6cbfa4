"""Builders shared by tests (no tests here): small datasets, captures and submissions written by hand,
with the truth the code under test must recover. Importable because tests/ (conftest's folder) is on
sys.path under pytest's default import mode."""
