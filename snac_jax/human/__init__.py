"""The human baseline: a game in which a person plays a SNAC task with the agent's view.

`game` (pure logic: key bindings, sessions, the screen), `records` (the JSONL of episodes and
their summary), `window` (the pygame loop). Start it with `snac play --task T`.
"""
