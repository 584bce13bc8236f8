"""Error types raised by library code. Only the CLI turns them into exit codes and one-line messages."""


class NvpError(Exception):
    """Base class: a problem with the user's input or environment, explained in the message."""


class MediaError(NvpError):
    """A media file is missing, unreadable, corrupt, or lacks the stream that is needed."""


class NoFaceError(NvpError):
    """No trackable face was found where one was required."""


class FormatError(NvpError):
    """A saved nvp file (manifest, npz) is missing, corrupt or of an unsupported version."""
