"""The pieces the learners share: what a network reads, the networks, targets, the replay loop."""
