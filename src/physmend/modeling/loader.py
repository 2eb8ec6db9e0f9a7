"""Load a user's model from a builder reference: ``package.module:function`` or ``path/file.py:function``."""

from __future__ import annotations

import importlib
import importlib.util
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from physmend.modeling.errors import ModelError
from physmend.modeling.model import Model


def _import_builder(ref: str) -> Any:
    if ":" not in ref:
        raise ModelError(
            f"model.builder must look like 'package.module:function' or 'path/to/file.py:function', "
            f"but got {ref!r}"
        )
    where, func = ref.rsplit(":", 1)
    if where.endswith(".py") or "/" in where or "\\" in where:
        path = Path(where).expanduser().resolve()
        if not path.is_file():
            raise ModelError(f"model.builder: model file {str(path)!r} does not exist (from {ref!r})")
        mod_name = f"physmend_user_model_{abs(hash(str(path)))}"
        spec = importlib.util.spec_from_file_location(mod_name, path)
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[mod_name] = module
        try:
            spec.loader.exec_module(module)
        except Exception as exc:
            raise ModelError(f"model.builder: importing {str(path)!r} failed: {where_in_user_code(exc)}") from None
    else:
        try:
            module = importlib.import_module(where)
        except ImportError as exc:
            raise ModelError(f"model.builder: cannot import module {where!r} (from {ref!r}): {exc}") from exc
    try:
        return getattr(module, func)
    except AttributeError:
        raise ModelError(f"model.builder: {where!r} has no function {func!r}") from None


def where_in_user_code(exc: BaseException, *, with_error: bool = True) -> str:
    """``"ValueError at /path/model.py, line 12 (in build): message"``: the error and the innermost
    line of the user's code (outside physmend and installed packages) it passed through."""
    import traceback

    if isinstance(exc, SyntaxError) and exc.filename:
        where = f"{exc.filename}, line {exc.lineno}"
        return f"{type(exc).__name__} at {where}: {exc.msg}" if with_error else f"at {where}"
    ours = Path(__file__).resolve().parents[1]
    frames = [f for f in traceback.extract_tb(exc.__traceback__)
              if not Path(f.filename).resolve().is_relative_to(ours) and "site-packages" not in f.filename
              and not f.filename.startswith("<frozen")]
    where = f"at {frames[-1].filename}, line {frames[-1].lineno} (in {frames[-1].name})" if frames else ""
    if not with_error:
        return where
    return f"{type(exc).__name__} {where}: {exc}".replace("  ", " ")


def load_model(builder: str, options: Mapping[str, Any] | None = None, corrections: str | None = None) -> Model:
    """Call the builder named by ``builder`` with keyword ``options`` and return its :class:`Model`.

    ``corrections``: an accepted corrections file (see :mod:`physmend.modeling.corrections`)
    applied on top of the built model.
    """
    fn = _import_builder(builder)
    try:
        model = fn(**dict(options or {}))
    except TypeError as exc:
        if exc.__traceback__ is not None and exc.__traceback__.tb_next is None:  # the call itself: the options
            raise ModelError(f"model.builder {builder!r} rejected model.options {dict(options or {})}: {exc}") from None
        raise ModelError(f"model.builder {builder!r} failed: {where_in_user_code(exc)}") from None
    except ModelError as exc:  # physmend's modeling API refused something the builder asked for
        raise ModelError(f"model.builder {builder!r}: {exc} ({where_in_user_code(exc, with_error=False)})") from None
    except Exception as exc:  # noqa: BLE001 - the user's own code failed: their error, their file and line
        raise ModelError(f"model.builder {builder!r} failed: {where_in_user_code(exc)}") from None
    if not isinstance(model, Model):
        raise ModelError(
            f"model.builder {builder!r} must return a physmend.modeling.Model, but returned {type(model).__name__}"
        )
    from physmend.modeling.fingerprint import remember

    remember(builder, dict(options or {}), model)  # the model as built, before any corrections file
    if corrections:
        from physmend.modeling.corrections import apply_corrections, read_corrections

        items, meta = read_corrections(corrections)
        model = apply_corrections(model, items, where=str(corrections), parameters=meta["parameters"])
    return model
