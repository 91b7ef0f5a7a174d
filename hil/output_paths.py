"""Checks of output paths before a HIL command runs (issue 17), raising ``hil.errors.OutputPathError``.

The checks are ``models.output_paths``' (one implementation, in the lowest layer that
writes files); this module binds them to the HIL's error, so ``hil`` commands catch one
``HilError`` hierarchy.
"""
from __future__ import annotations

from functools import partial

from hil.errors import OutputPathError
from models import output_paths as _checks

#: Refuse a path that is (or links to) one of the inputs.
check_not_input = partial(_checks.check_not_input, error=OutputPathError)
#: An output file: folder exists and writable, not an input, not a folder, new unless replace.
check_output_file = partial(_checks.check_output_file, error=OutputPathError)
#: An output folder: parent exists, holds no other run's outputs unless replace.
check_output_folder = partial(_checks.check_output_folder, error=OutputPathError)
