"""Objects kept in a uniform cell grid as doubly linked lists (``head`` per cell, ``nxt``/``prv`` per
object, ``cell_of`` the object's cell or -1): the one mechanism under the greedy walk's hypothesis grid
and the batch cluster index."""

from __future__ import annotations

from numba import njit


@njit(cache=True, inline="always")
def unlink(head, nxt, prv, cell_of, c: int) -> None:
    """Take object ``c`` out of its cell's list (nothing if it is in none)."""
    k = cell_of[c]
    if k < 0:
        return
    if prv[c] >= 0:
        nxt[prv[c]] = nxt[c]
    else:
        head[k] = nxt[c]
    if nxt[c] >= 0:
        prv[nxt[c]] = prv[c]
    nxt[c] = -1
    prv[c] = -1
    cell_of[c] = -1


@njit(cache=True, inline="always")
def relink(head, nxt, prv, cell_of, c: int, k: int) -> None:
    """Move object ``c`` to the front of cell ``k``'s list."""
    unlink(head, nxt, prv, cell_of, c)
    nxt[c] = head[k]
    if head[k] >= 0:
        prv[head[k]] = c
    head[k] = c
    cell_of[c] = k
