"""Rules between parameters that openapi.yaml states in words because OpenAPI cannot state them in a schema.

schemathesis loads this file (SCHEMATHESIS_HOOKS, set by tests/contract_schemathesis.rs) and does not generate
"valid" requests that break them; each rule is in the description of the parameters concerned.
"""

import schemathesis


def _given(query, name):
    return query is not None and query.get(name) is not None


@schemathesis.serializer("multipart/related")
def multipart_related(ctx, value):
    """STOW-RS bodies are bytes as generated (the schema is a string): ctrecon parses the parts itself."""
    if isinstance(value, bytes):
        return value
    return str(value).encode("utf-8")


@schemathesis.hook
def filter_case(ctx, case):
    op = case.operation
    # Preset, Ww, Wl: a window is either a `preset` or `ww` with `wl` (422 invalid_parameter otherwise).
    preset, ww, wl = (_given(case.query, n) for n in ("preset", "ww", "wl"))
    if (preset and (ww or wl)) or ww != wl:
        return False
    # POST /v1/series: `upload` appends one application/dicom body (with a form or ZIP: 400 invalid_query).
    if op.method.upper() == "POST" and op.path == "/v1/series" and _given(case.query, "upload"):
        return case.media_type == "application/dicom"
    return True
