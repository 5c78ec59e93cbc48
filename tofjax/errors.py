"""The one error type the ``tofjax`` command turns into a one-line message.

Every error caused by what the user gave (a config, a capture, a scene, a rig, a
trained model that does not fit the data) derives from :class:`UserError`, so the CLI
catches them all in one place and never shows a traceback for them.
"""


class UserError(ValueError):
    """Bad input from the user: shown as one line, exit code 2."""
