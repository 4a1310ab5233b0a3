"""File formats: CONTACTS, PRIOR and sequence JSON (:mod:`.jsonfiles`), the model file (npz,
checks, memory map: :mod:`.modelfile`), the cache of models built from named objects
(:mod:`.cache`), and the JSON the CLI writes (:mod:`.output`).

Paper equation: the measured contact plane of eq. (1), d̃ = -ñᵀx̃, is what a CONTACTS file
gives (points and normals; contactpose.contacts.Contacts holds them).
"""

from contactpose.io.jsonfiles import parse_contacts, parse_prior, read_contacts, read_prior, read_sequence, write_json
from contactpose.io.output import load_schema, schema_path

__all__ = ["load_schema", "parse_contacts", "parse_prior", "read_contacts", "read_prior", "read_sequence",
           "schema_path", "write_json"]
