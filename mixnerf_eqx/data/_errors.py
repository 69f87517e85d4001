"""The one error type that the dataset loaders raise."""


class DatasetError(ValueError):
    """A dataset that cannot be loaded as asked.

    The message names the file or folder at fault and says what to do about it, so that the
    command-line tools can print it as it is, without a traceback.
    """


class UnknownSceneError(DatasetError):
    """A scene that is neither one of its benchmark's nor a folder of the dataset's root."""
