"""File formats: CONTACTS and PRIOR JSON, and the model file (npz, checks, memory map)."""
