"""`felis.logs`."""
