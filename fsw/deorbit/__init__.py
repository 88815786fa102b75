"""The de-orbit kit's flight side: sequencer (interlocks, recovery, safe mode), discrete controller,
energy ledger, and the kit that composes them with the drivers and the ground commands."""
