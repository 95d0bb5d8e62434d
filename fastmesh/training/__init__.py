"""Training: a generic loop (``loop``) and one task module per network."""
