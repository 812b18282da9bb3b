"""Diagnostic commands (not studies): `python -m dslearn.tools.<name>`."""
