"""What a synthesis compiles after `engine.synthesis.warm` has warmed its kind, in a fresh process:
`python -m tests.engine.synthesis.warm_probe ROOT` prints, as JSON, for each kind of synthesis
(`VARIANTS`), the kernel signatures its syntheses over ROOT's index added to those the warming
left (each `module.kernel`: its new signatures), and what the warming itself added; the first
should be empty. Run by tests/engine/synthesis/test_warm.py. No Ray.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
from typing import Any

import numpy as np

#: Each kind of synthesis the warming tells apart (`warm.variant`), as `synthesize`'s options,
#: each in the order warmed: each warming must cover its own (the first its layer plans too).
VARIANTS: dict[str, dict[str, Any]] = {
    "designed": {
        "constraints": {"max_link_ratio": 20.0, "max_layers": 6},
        "min_transmission_deg": 30.0,
    },
    "stroke": {"partial": True},
    "timed": {"timing": True},
    "front": {"front": True},
    "closed": {},
}
#: Counted work of each probing synthesis (its retrievals' kernels), and of each refinement of
#: FEW retrieved candidates, enough for every pass over so few: the short, middle and long
#: passes, the polish's coupler points and the restarts.
ITERATIONS, FEW, FEW_ITERATIONS = 200, 4, 600


def signatures() -> dict[str, set[str]]:
    """Every compiled signature of every numba kernel of links_ray's loaded modules."""
    from numba.core.dispatcher import Dispatcher

    found: dict[str, set[str]] = {}
    for name, module in list(sys.modules.items()):
        if not name.startswith("links_ray") or module is None:
            continue
        for attribute, value in list(vars(module).items()):
            if isinstance(value, Dispatcher):
                key = f"{value.py_func.__module__}.{attribute}"
                found.setdefault(key, set()).update(str(s) for s in value.signatures)
    return found


def added(before: dict[str, set[str]], after: dict[str, set[str]]) -> dict[str, list[str]]:
    """The signatures in `after` that `before` lacks, by kernel."""
    return {
        key: sorted(sigs - before.get(key, set()))
        for key, sigs in after.items()
        if sigs - before.get(key, set())
    }


def drawings() -> dict[str, np.ndarray]:
    """Two closed drawings and a stroke, in screen-like units."""
    t = np.linspace(0.0, 2.0 * math.pi, 60, endpoint=False)
    ellipse = np.column_stack([300 + 120 * np.cos(t), 200 + 50 * np.sin(t)])
    bean = np.column_stack([np.cos(t) + 0.3 * np.cos(2 * t), 0.6 * np.sin(t)])
    return {"ellipse": ellipse, "bean": bean, "stroke": ellipse[:25]}


def probe(root: str) -> dict[str, Any]:
    """For each variant: what warming it added, and what its syntheses added after it."""
    from links_ray.engine.synthesis.options import SynthesisOptions
    from links_ray.engine.synthesis.pipeline import refine_retrieved, synthesize
    from links_ray.engine.synthesis.target import as_target
    from links_ray.engine.synthesis.warm import warm_synthesis
    from links_ray.search.index import RetrievalIndex

    index = RetrievalIndex.open(root)
    shapes = drawings()
    report: dict[str, Any] = {}
    for name, asked in VARIANTS.items():
        partial = asked.get("partial", False)
        queries = [shapes["stroke"]] if partial else [shapes["ellipse"], shapes["bean"]]
        options = SynthesisOptions(k=3, seed=0, iterations=ITERATIONS, **asked)
        before = signatures()
        warm_synthesis(as_target(queries[0], partial), options, index)
        warmed = signatures()
        few = dataclasses.replace(options, k=2, iterations=FEW_ITERATIONS)
        for query in queries:
            synthesize(index, query, options=options)
            refine_retrieved(query, index.retrieve(query, FEW), few)
        report[name] = {
            "warming": sorted(added(before, warmed)),
            "after": added(warmed, signatures()),
        }
    return report


if __name__ == "__main__":
    print(json.dumps(probe(sys.argv[1])))
