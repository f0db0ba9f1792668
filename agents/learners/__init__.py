"""The learners the paper trained: one module per algorithm id, each read top to bottom."""
