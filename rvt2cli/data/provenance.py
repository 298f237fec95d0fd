"""Which software wrote an episode: the versions stored in its metadata."""

from importlib.metadata import PackageNotFoundError, version

from rvt2cli import __version__


def software_versions(*distributions: str) -> dict[str, str]:
    """rvt2's own version (also when it runs from a source tree, with no installed metadata) and those
    of the installed `distributions` ("unknown" for one without metadata)."""
    versions = {"rvt2": __version__}
    for name in distributions:
        try:
            versions[name] = version(name)
        except PackageNotFoundError:
            versions[name] = "unknown"
    return versions
