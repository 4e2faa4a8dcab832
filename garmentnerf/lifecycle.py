"""Objects that hold resources (GL objects, threads, files) until they are closed."""

from __future__ import annotations

from typing import Self

__all__ = ["Closeable"]


class Closeable:
    """Base of an object that frees what it holds in :meth:`close`; ``with obj:`` closes it at
    the end of the block, also when the block raises."""

    def close(self) -> None:
        raise NotImplementedError

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
