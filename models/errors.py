"""Exception hierarchy of the ``models`` package.

Every error raised on bad input by code under ``models/`` derives from ``ModelError``;
other modules of the package add their own subclasses next to their code.
"""
from __future__ import annotations


class ModelError(Exception):
    """Base of all errors raised by the models package."""


class VehicleParamsError(ModelError):
    """A vehicle parameter file or override is missing a field or has a bad value."""


class VehicleCommandError(ModelError):
    """A command or step size given to the plant is not usable (NaN, dt <= 0, ...)."""


class VehicleDivergedError(ModelError):
    """The plant state became non-finite (should never happen with valid parameters)."""


class DatasetError(ModelError):
    """A data set file is malformed; the message names the file and, where known, the column."""


class OutputPathError(ModelError):
    """An output file or folder cannot be used (``models.output_paths``): it is one of the
    command's inputs, exists without the replace option, or its folder is missing or not
    writable."""


class KoopmanError(ModelError):
    """A Koopman artefact or model definition is unusable (names the file / field).

    Raised by ``models/koopman.py`` and its parts (``koopman_artifact``, ``koopman_dictionary``),
    and importable from ``models.koopman``."""
