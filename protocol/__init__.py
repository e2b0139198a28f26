"""Wire protocol: message models, codec and clock math (pure, no I/O)."""
