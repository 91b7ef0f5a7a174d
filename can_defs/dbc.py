"""Location and loading of the contract's DBC file."""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import cantools

from can_defs.errors import DbcLoadError

DBC_PATH: Path = Path(__file__).resolve().parent / "vehicle.dbc"
#: Bytes of a DBC file (the contract's is 12 kB); the C ECU reads at most as many (firmware/src/ecu_main.c).
DBC_FILE_MAX_BYTES = 4 * 1024 * 1024
"""The CAN matrix of the contract (`docs/can-contract.md`), for this codec and third-party nodes."""


@lru_cache(maxsize=None)
def load_database(path: Path = DBC_PATH) -> cantools.database.can.Database:
    """Load the DBC with cantools' strict checks (overlapping or out-of-frame signals are
    refused). Cached: the file is parsed once per process. At most
    ``DBC_FILE_MAX_BYTES`` are read (a DBC given as ``/dev/zero`` is one error)."""
    try:
        with Path(path).open("rb") as handle:  # at most one byte past the bound is ever read
            raw = handle.read(DBC_FILE_MAX_BYTES + 1)
        if len(raw) > DBC_FILE_MAX_BYTES:
            raise DbcLoadError(f"cannot load DBC {path}: larger than {DBC_FILE_MAX_BYTES} bytes "
                               "(the limit of this file)")
        text = raw.decode("cp1252")  # cantools' encoding of a DBC
        database = cantools.database.load_string(text, database_format="dbc", strict=True)
    except (OSError, UnicodeDecodeError, cantools.database.UnsupportedDatabaseFormatError,
            cantools.database.Error) as error:
        raise DbcLoadError(f"cannot load DBC {path}: {error}") from error
    if not isinstance(database, cantools.database.can.Database):
        raise DbcLoadError(f"{path} is not a CAN database")
    return database
