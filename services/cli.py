"""The ``stockpile`` command (placeholder, replaced below)."""
def main() -> int:
    return 0
