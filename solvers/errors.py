"""The small exception tree of greyfit; the service maps each class to one HTTP answer."""


class FitError(Exception):
    """Base of every error greyfit raises on purpose; `field` names where the fix goes."""

    def __init__(self, message: str, field: str | None = None):
        self.field = field
        self.message = message
        super().__init__(f"{field}: {message}" if field else message)


class ModelDefinitionError(FitError):
    """The model cannot be compiled: syntax, unknown names, missing equations."""


class DataError(FitError):
    """The experiments do not fit the model or contain unusable values."""


class CovarianceUnavailable(FitError):
    """The information matrix is singular or indefinite; the note says which combination."""


class DataFileError(DataError):
    """A measurement file that cannot be read as a record: the message is one line naming the file,
    the column and the row."""

    def __init__(self, message: str):
        super().__init__(message)
