"""HDF5 artifacts: atomic writes, provenance, schema checks.

Every stage writes one HDF5 file through :func:`write_artifact`: the content goes to a
temporary file in the target's folder and is renamed over the final name only once complete,
so a crash or a bad input never leaves a half-written or clobbered artifact. Root attributes
record what made the file (schema, version, time, config, input hashes, seed). Readers go
through :func:`open_artifact`, which checks the schema and names the file, the expected and the
found schema on a mismatch.

Layout, one module per concern:

================  =========================================================================
``schema``        artifact kinds and their schema versions (:data:`SCHEMAS`, :data:`READABLE`)
``provenance``    root attributes: writing, reading back, :func:`is_up_to_date`
``reading``       :func:`open_artifact`, :func:`get`, :class:`LazyUnits`, :func:`verify_artifact`
``locks``         the output lock (:func:`output_lock`, :func:`locks_output`)
``temporaries``   :func:`remove_stale_temporaries`
``writing``       :func:`write_artifact`, :func:`put`, :func:`set_attrs`, :func:`json_attr`,
                  :func:`file_type`, :func:`check_outputs_not_inputs`
================  =========================================================================
"""
from .locks import lock_path, locks_output, output_lock
from .provenance import (check_same_version, file_sha256, input_records, is_up_to_date,
                         read_provenance, set_provenance, utc_now)
from .reading import LazyUnits, get, get_shape, open_artifact, verify_artifact
from .schema import READABLE, SCHEMAS, schema_name
from .temporaries import remove_stale_temporaries
from .writing import (COMPACT_LIBVER, check_outputs_not_inputs, file_type, json_attr, put,
                      replacing, same_file, set_attrs, write_artifact)

__all__ = ["COMPACT_LIBVER", "SCHEMAS", "READABLE", "schema_name", "file_sha256",
           "input_records", "write_artifact", "same_file", "check_outputs_not_inputs",
           "lock_path", "output_lock", "locks_output", "remove_stale_temporaries", "utc_now",
           "set_provenance", "open_artifact", "put", "get", "get_shape", "LazyUnits",
           "read_provenance", "is_up_to_date", "check_same_version", "verify_artifact",
           "json_attr", "set_attrs", "file_type", "replacing"]
