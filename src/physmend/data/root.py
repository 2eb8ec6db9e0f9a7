"""Where a data config's telemetry lives: a folder path, or ``pkg://<package>/<subdir>``, a folder
inside an installed package."""

from __future__ import annotations

import importlib.resources
from pathlib import Path
from typing import Any

from physmend.data.errors import DataError

PKG_SCHEME = "pkg://"


def resolve_root(root: Any, *, config_name: str = "data") -> Path:
    """The absolute folder named by ``root``.

    ``pkg://<package>/<subdir>`` is a folder inside an installed package (``importlib.resources``);
    anything else is a path: ``~`` expands and relative paths resolve against the current working
    directory. The folder itself is not required to exist here (a missing file is reported with
    its resolved path when it is read).
    """
    if isinstance(root, Path):
        root = str(root)
    if not isinstance(root, str) or not root.strip():
        raise DataError(
            f"data config {config_name!r}: `root` must be a folder path or "
            f"'pkg://<package>/<subdir>', but got {root!r}"
        )
    if root.startswith(PKG_SCHEME):
        rest = root[len(PKG_SCHEME) :]
        package, _, subdir = rest.partition("/")
        if not package:
            raise DataError(
                f"data config {config_name!r}: `root` {root!r} must name a package, "
                "as in 'pkg://my_package/telemetry'"
            )
        try:
            base = importlib.resources.files(package)
        except Exception as exc:  # ModuleNotFoundError, TypeError for non-packages, import errors
            raise DataError(
                f"data config {config_name!r}: `root` {root!r} names package {package!r}, "
                f"which is not importable: {exc}"
            ) from None
        target = base.joinpath(*[p for p in subdir.split("/") if p]) if subdir else base
        return _traversable_path(target, root, config_name)
    return Path(root).expanduser().resolve()


def _traversable_path(target: Any, root: str, config_name: str) -> Path:
    if isinstance(target, Path):
        return target.resolve()
    paths = getattr(target, "_paths", None)  # namespace package: MultiplexedPath
    if paths:
        return Path(paths[0]).resolve()
    raise DataError(
        f"data config {config_name!r}: `root` {root!r} is not a folder on the file system "
        f"(resource {target!r}); install the package unzipped or give a path"
    )
