"""The kinds of joint (`node_types` entries), as the LINKS dataset numbers them."""

from __future__ import annotations

#: A fixed joint (a pivot on the ground), a simple (moving) joint, and the crank's driven tip.
FIXED, SIMPLE, ACTUATED = 0, 1, 2
