"""The error of the bag layer: one type, so every caller catches bag problems in one place."""


class BagError(Exception):
    """A bag cannot be written, read or recovered; the message says why and what to do."""
