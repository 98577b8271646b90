"""What a person most likely meant by a name that is not there: "did you mean".

People type names as manuals and labels write them: in capitals (``CO2``), cut short
(``temp``), or as a part of a longer id (``irnet`` for ``net-irnet-pro``). Each is tried
before spelling mistakes (difflib), so every "did you mean" in rtupoll finds the same.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable

PART = 3  # the shortest prefix or part of a name that is taken as meant


def close_names(word: str, known: Iterable[str], n: int = 1) -> list[str]:
    """Up to ``n`` names of ``known`` that ``word`` likely means, the likeliest first.

    In order: the same name in other capitals or with ``-``/``_``/space swapped; names it
    begins (shortest first); names it is a part of; then close spellings.
    """
    names = list(dict.fromkeys(known))
    key = _fold(word)
    folded = {name: _fold(name) for name in names}
    same = [name for name in names if folded[name] == key]
    if same:
        return same[:n]
    if len(key) >= PART:
        begun = sorted((m for m in names if folded[m].startswith(key)), key=len)
        inside = sorted((m for m in names if key in folded[m] and m not in begun), key=len)
        if begun or inside:
            return [*begun, *inside][:n]
    by_fold = {fold: name for name, fold in folded.items()}
    return [by_fold[m] for m in difflib.get_close_matches(key, list(by_fold), n=n)]


def _fold(name: str) -> str:
    return name.strip().lower().replace("-", "_").replace(" ", "_")
