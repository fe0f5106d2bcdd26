"""Edge services and the ``stockpile`` command line (top of the import chain)."""
