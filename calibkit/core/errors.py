"""The one exception type for problems a user can cause and fix."""


class UserError(Exception):
    """A bad file, a missing camera, a wand never seen: the message is written for the user.

    The CLI catches it, prints the message as one line and exits non-zero; bugs are not
    wrapped in it and still raise with a traceback.
    """
