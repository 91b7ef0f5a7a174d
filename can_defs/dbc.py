"""Location and loading of the contract's DBC file."""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import cantools

from can_defs.errors import DbcLoadError

DBC_PATH: Path = Path(__file__).resolve().parent / "vehicle.dbc"
"""The CAN matrix of the contract (`docs/can-contract.md`), for this codec and third-party nodes."""


@lru_cache(maxsize=None)
def load_database(path: Path = DBC_PATH) -> cantools.database.can.Database:
    """Load the DBC with cantools' strict checks (overlapping or out-of-frame signals are
    refused). Cached: the file is parsed once per process. At most
    ``DBC_FILE_MAX_BYTES`` are read (a DBC given as ``/dev/zero`` is one error)."""
    from models.input_files import DBC_FILE_MAX_BYTES, InputFileError, read_bounded

    try:
        text = read_bounded(path, DBC_FILE_MAX_BYTES).decode("cp1252")  # cantools' encoding of a DBC
        database = cantools.database.load_string(text, database_format="dbc", strict=True)
    except InputFileError as error:
        raise DbcLoadError(f"cannot load DBC {error}") from None
    except (OSError, UnicodeDecodeError, cantools.database.UnsupportedDatabaseFormatError,
            cantools.database.Error) as error:
        raise DbcLoadError(f"cannot load DBC {path}: {error}") from error
    if not isinstance(database, cantools.database.can.Database):
        raise DbcLoadError(f"{path} is not a CAN database")
    return database
