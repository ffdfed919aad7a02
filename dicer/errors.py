"""The one error type users see: a one-line message naming the file, the problem and the fix."""


class DicerError(Exception):
    """Bad input or a stage that cannot succeed; the CLI prints ``error: <message>`` and exits 2."""
