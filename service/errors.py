"""Errors the engine and the store raise; the HTTP layer turns each into one status code."""


class InvalidPoints(ValueError):
    """The points cannot be used (422). The message tells the caller what to change."""


class UnknownReference(KeyError):
    """A reference name that is not registered (404)."""

    def __str__(self) -> str:  # KeyError quotes its argument; we want the plain message
        return str(self.args[0]) if self.args else "unknown reference"


class EmptyGallery(RuntimeError):
    """No reference is registered, so there is nothing to recognise (409)."""


class ReferenceExists(RuntimeError):
    """A reference of that name is registered and replace was not asked for (409)."""


class StoreUnavailable(RuntimeError):
    """The gallery's database cannot be reached or used right now (503); worth a retry."""


class StoreFull(RuntimeError):
    """The gallery's disk (or database) has no room for a write (507); nothing was stored."""
