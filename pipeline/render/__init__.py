"""The shared rendering layer: rays through pixel centres and the one mesh ray-caster."""
