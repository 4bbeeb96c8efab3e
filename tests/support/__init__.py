"""Helpers shared by the tests (``from support.helpers import ...``); not part of
the add-on, and not collected by pytest."""
