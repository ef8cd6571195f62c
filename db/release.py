"""The running release, for ``pipesentry_build_info``: the package version and the schema it expects."""
from __future__ import annotations

import importlib.metadata
import platform

from db import migrate


def release_labels() -> dict[str, str]:
    """``version`` (the installed pipesentry package), ``schema_revision`` (the Alembic head this code
    writes), ``python_version``: the labels of ``pipesentry_build_info`` in every process."""
    try:
        version = importlib.metadata.version("pipesentry")
    except importlib.metadata.PackageNotFoundError:  # run from a source tree that is not installed
        version = "unknown"
    return {"version": version, "schema_revision": migrate.head_revision(), "python_version": platform.python_version()}
