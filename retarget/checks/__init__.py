"""Solver-independent checks of a reference: dynamic feasibility, verification against its
demonstration (penetration, limits, holds), the ground and terrain it stands on, and
``otr clear-ground``'s arm clearance."""
