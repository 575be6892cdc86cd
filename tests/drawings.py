"""Reading back the fabrication files: a DXF by its group codes, independently of the writer."""

from __future__ import annotations


def dxf_pairs(text: str) -> list[tuple[int, str]]:
    """(group code, value) pairs, one line each."""
    lines = text.splitlines()
    assert len(lines) % 2 == 0
    return [(int(lines[k]), lines[k + 1]) for k in range(0, len(lines), 2)]


def dxf_sections(text: str) -> dict[str, list[list[tuple[int, str]]]]:
    """Each section's records: the pairs from one group code 0 to the next."""
    pairs = dxf_pairs(text)
    assert pairs[-1] == (0, "EOF")
    sections: dict[str, list[list[tuple[int, str]]]] = {}
    k = 0
    while pairs[k] != (0, "EOF"):
        assert pairs[k] == (0, "SECTION") and pairs[k + 1][0] == 2
        name, k = pairs[k + 1][1], k + 2
        records: list[list[tuple[int, str]]] = []
        while pairs[k] != (0, "ENDSEC"):
            if pairs[k][0] == 0 or not records:
                records.append([])
            records[-1].append(pairs[k])
            k += 1
        sections[name] = records
        k += 1
    return sections


def field(record: list[tuple[int, str]], code: int) -> str:
    """The one value of group code `code` in a record."""
    values = [value for c, value in record if c == code]
    assert len(values) == 1, (code, record)
    return values[0]


def dxf_header(sections: dict[str, list[list[tuple[int, str]]]]) -> dict[str, str]:
    """Each header variable (group code 9) and its first value."""
    pairs = [pair for record in sections["HEADER"] for pair in record]
    return {pairs[k][1]: pairs[k + 1][1] for k in range(len(pairs) - 1) if pairs[k][0] == 9}
