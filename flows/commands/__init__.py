"""Command implementations of the ``mobileocc`` CLI that are more than a call into a flow."""
