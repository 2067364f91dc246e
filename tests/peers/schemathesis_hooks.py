"""Hooks of tests/contract_schemathesis.rs (schemathesis loads this file through SCHEMATHESIS_HOOKS).

1. Rules between parameters that openapi.yaml states in words because OpenAPI cannot state them in a schema:
   "valid" requests that break them are not generated (`filter_case`).
2. Things that exist: the test seeds the server (datasets, jobs, series, uploads, rules, a delivery, a stored
   study, a peer) and names them in the file CTRECON_CONTRACT_SEED. Most valid requests are made to name a seeded
   thing instead of a random id, and STOW-RS, `POST /v1/series` and `POST /v1/sinograms` get real bodies, so that
   the checks see success answers, not only 404s (`before_call`). Requests generated as invalid are sent as
   generated, and so are the stateful phase's requests (they follow the document's links). The choice follows a
   hash of the generated request, so a run is reproducible.
3. A tally of every answer (CTRECON_CONTRACT_TALLY), from which the test counts the operations that reached a 2xx.
"""

import json
import os
import re
import zlib

import schemathesis

UUID = re.compile(r"^[0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12}$")


def _load_seed():
    path = os.environ.get("CTRECON_CONTRACT_SEED")
    if not path:
        return None
    with open(path, encoding="utf-8") as f:
        seed = json.load(f)
    with open(seed["dicom_file"], "rb") as f:
        seed["dicom_bytes"] = f.read()
    with open(seed["npy_file"], "rb") as f:
        seed["npy_bytes"] = f.read()
    return seed


SEED = _load_seed()

# Which seeded things each `{id}`-like path parameter of an operation names. Operations that delete or use up
# what they name get their own ("spare") things, so that the others keep theirs.
ID_KIND = [
    (("DELETE", "/v1/datasets/{id}"), "dataset_spare"),
    (("DELETE", "/v1/jobs/{id}"), "job_spare"),
    (("DELETE", "/v1/series/{id}"), "series_spare"),
    (("DELETE", "/v1/uploads/{id}"), "upload_spare"),
    (("POST", "/v1/uploads/{id}/complete"), "upload_complete"),
    ((None, "/v1/datasets/{id}"), "dataset"),
    ((None, "/v1/jobs/{id}/result/mesh.stl"), "volume_job"),
    ((None, "/v1/jobs/{id}/result/series.zip"), "volume_job"),
    ((None, "/v1/jobs/{id}/result/products/{index}"), "volume_job"),
    ((None, "/v1/jobs/{id}"), "job"),
    ((None, "/v1/series/{id}"), "series"),
    ((None, "/v1/uploads/{id}"), "upload"),
    ((None, "/v1/deliveries/{id}"), "delivery"),
]


def _id_kind(method, path):
    for (m, prefix), kind in ID_KIND:
        if (m is None or m == method) and (path == prefix or path.startswith(prefix + "/")):
            return kind
    return None


def _given(query, name):
    return query is not None and query.get(name) is not None


def _positive(case):
    meta = getattr(case, "_meta", None)
    return meta is None or meta.generation.mode.is_positive


def _stateful(case):
    """The stateful phase follows the document's links with the ids the server answered: left as it is."""
    meta = getattr(case, "_meta", None)
    return meta is not None and str(meta.phase.name) == "stateful"


def _draw(case, salt):
    """A number 0..99 that depends only on the generated request."""
    text = repr((salt, case.path_parameters, case.query, case.body if isinstance(case.body, (dict, list, str, int, float)) else None))
    return zlib.crc32(text.encode("utf-8")) % 100


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


def _stow_body(case, seed):
    boundary = "contract-hook-boundary"
    body = (
        f"--{boundary}\r\nContent-Type: application/dicom\r\n\r\n".encode()
        + seed["dicom_bytes"]
        + f"\r\n--{boundary}--\r\n".encode()
    )
    case.body = body
    case.headers = dict(case.headers or {})
    case.headers["Content-Type"] = f'multipart/related; type="application/dicom"; boundary={boundary}'


@schemathesis.hook
def before_call(ctx, case, kwargs):
    method, path = case.operation.method.upper(), case.operation.path
    # The list-wide event stream never ends by itself: every request asks it to end after `ready`.
    if method == "GET" and path == "/v1/events":
        seconds = (case.query or {}).get("seconds")
        if seconds is None or (isinstance(seconds, int) and not isinstance(seconds, bool) and 0 <= seconds <= 86400):
            case.query = dict(case.query or {})
            case.query["seconds"] = 0
        return
    if SEED is None or not _positive(case) or _stateful(case):
        return
    seed = SEED
    params = case.path_parameters or {}
    if params and _draw(case, "path") < 75:
        params = dict(params)
        kind = _id_kind(method, path)
        if kind and UUID.match(str(params.get("id", ""))):
            params["id"] = seed[kind][0]
        if "name" in params:
            params["name"] = seed["rule_spare" if method == "DELETE" else "rule"][0]
        if "ae_title" in params:
            params["ae_title"] = seed["peer"][0]
        if "study" in params:
            params["study"] = seed["study"][0]
        if "series" in params:
            params["series"] = seed["series_uid"][0]
        if "instance" in params:
            params["instance"] = seed["instance"][0]
        if "frame" in params:
            params["frame"] = 1
        if "index" in params:
            params["index"] = params["index"] % 2 if isinstance(params["index"], int) else 0
        case.path_parameters = params
    if method == "POST" and path.startswith("/dicom-web/studies") and _draw(case, "stow") < 50:
        _stow_body(case, seed)
    elif method == "POST" and path == "/v1/series" and case.media_type == "application/dicom":
        if _draw(case, "series") < 50:
            case.body = seed["dicom_bytes"]
            case.query = {k: v for k, v in (case.query or {}).items() if k != "upload"}
    elif method == "POST" and path == "/v1/sinograms" and case.media_type == "application/x-npy":
        if _draw(case, "sinogram") < 50:
            case.body = seed["npy_bytes"]
            case.query = {"geometry": seed["geometry"]}
            case.headers = {k: v for k, v in (case.headers or {}).items() if k.lower() != "x-ctrecon-geometry"}
    elif method == "POST" and path == "/v1/jobs" and _draw(case, "job") < 10:
        case.body = seed["job_body"]
    elif method == "POST" and path == "/v1/deliveries" and isinstance(case.body, dict):
        if _draw(case, "delivery") < 75 and UUID.match(str(case.body.get("job_id", ""))):
            case.body = dict(case.body, job_id=seed["volume_job"][0], destination=seed["peer"][0])


@schemathesis.hook
def after_call(ctx, case, response):
    """Each answer's operation, status and seconds, one line each, for the coverage count of the contract test."""
    tally = os.environ.get("CTRECON_CONTRACT_TALLY")
    if tally:
        with open(tally, "a", encoding="utf-8") as f:
            op = f"{case.operation.method.upper()} {case.operation.path}"
            f.write(f"{op} {response.status_code} {response.elapsed:.4f}\n")
