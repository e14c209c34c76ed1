"""One module per ``autocar`` command; each exposes ``register(app)``."""
