"""What the emulators' command lines (``jtc-hw emulate dynamixel``, ``jtc-hw emulate can``)
share: the ``--ids`` syntax.

One syntax for every bus: ``"1-6"``, ``"1,3,5"``, ``"1-3,7"``; each number in Python's
integer-literal syntax (decimal, or ``0x1F`` as CAN ids are often written). A family's own
id range (Dynamixel 0..252) is checked by passing it as ``valid``.
"""

from __future__ import annotations

__all__ = ["parse_ids"]


def parse_ids(text: str, valid: range | None = None) -> list[int]:
    """``"1-6"``, ``"1,3,5"``, ``"1-3,7"`` -> the ids, in the order given.

    Raises:
        ValueError: not of that form, no id, an id given twice, or one outside ``valid``.
    """
    ids: list[int] = []
    for part in text.split(","):
        part = part.strip()
        if "-" in part:
            low, high = (int(x, 0) for x in part.split("-", 1))
            if high < low:
                raise ValueError(f"empty id range {part!r}")
            ids.extend(range(low, high + 1))
        elif part:
            ids.append(int(part, 0))
    outside = valid is not None and any(i not in valid for i in ids)
    if not ids or len(set(ids)) != len(ids) or outside:
        within = f" in {valid.start}..{valid.stop - 1}" if valid is not None else ""
        raise ValueError(f"expected distinct ids{within} like 1-6 or 1,2,3, got {text!r}")
    return ids
