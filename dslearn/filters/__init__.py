"""Filter steps as pure functions (information form)."""
