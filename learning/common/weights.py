"""Writing a weights file of the gradient-trained nets (the IK nets, the PAE): one ``.npz`` of float32
arrays and a JSON ``__meta__`` document, replaced atomically; reading it is the skill's inference module
(numpy only, `felis.files.read_meta`).

The caller's own metadata rides along in the document beside the keys the file format reserves; a file
is refused before anything is written: a name not ending in ``.npz``, metadata that sets a reserved key or
is not JSON.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from felis.errors import FelisError, ParameterError
from felis.files import META_KEY, write_atomic
from felis.learning.common.jsonable import jsonable


def weights_target(path: str | Path, meta: Mapping[str, Any] | None, reserved: Iterable[str], file_what: str,
                   meta_what: str, error: type[FelisError]) -> tuple[Path, dict[str, Any]]:
    """(``path`` as a Path, a copy of ``meta``) once the name ends in ``.npz`` (else ``error``: "a
    ``file_what`` file must end in .npz") and ``meta`` sets none of the ``reserved`` keys (else
    ParameterError naming them, "``meta_what`` metadata may not set …")."""
    path = Path(path)
    if path.suffix != ".npz":
        raise error(f"{path}: a {file_what} file must end in .npz")
    meta = dict(meta or {})
    clash = [k for k in reserved if k in meta]
    if clash:
        raise ParameterError(f"{meta_what} metadata may not set the reserved key(s) {', '.join(clash)}")
    return path, meta


def write_weights(path: Path, arrays: dict[str, np.ndarray], doc: Mapping[str, Any], meta_what: str, what: str,
                  error: type[FelisError]) -> Path:
    """``arrays`` and ``doc`` as JSON under `META_KEY` (no NaN; numpy values, configs and paths as
    `jsonable` gives them; ParameterError "``meta_what`` metadata is not JSON-serialisable" otherwise),
    written atomically to ``path`` (`felis.files.write_atomic`: ``what``, ``error``); returns ``path``."""
    try:
        arrays[META_KEY] = np.array(json.dumps(doc, allow_nan=False, default=jsonable))
    except (TypeError, ValueError) as e:
        raise ParameterError(f"{meta_what} metadata is not JSON-serialisable: {e}") from None
    return write_atomic(path, lambda f: np.savez(f, **arrays), what, error)
