// The public HTTP API as the page calls it: the bearer token kept in sessionStorage, problem+json errors
// turned into readable messages, Server-Sent Events read from a fetch stream (EventSource cannot send the
// Authorization header), uploads with progress, authenticated downloads.

const KEY = 'ctrecon.token';

export function token() {
  return sessionStorage.getItem(KEY) || '';
}

export function setToken(t) {
  if (t) sessionStorage.setItem(KEY, t);
  else sessionStorage.removeItem(KEY);
}

/** An API failure with the problem's fields; status 0 when the server could not be reached. */
export class ApiError extends Error {
  constructor(status, title, detail, code, problem) {
    super(`${title}: ${detail}`);
    this.status = status;
    this.title = title;
    this.detail = detail;
    this.code = code;
    this.problem = problem || null;
    /** The fields the problem names: [{pointer, detail}] (RFC 6901 pointers into the request body). */
    this.errors = problem && Array.isArray(problem.errors) ? problem.errors : [];
  }
}

export function unreachable() {
  return new ApiError(0, 'Server unreachable',
    `The ctrecon server at ${location.origin} does not answer. Is it running?`, 'unreachable');
}

/** A 401: "Token needed" while no token was entered in this tab, "Token refused" once one was. */
export function unauthorized(p) {
  if (!token()) {
    return new ApiError(401, 'Token needed',
      'This server needs an API token. Enter it above; it is kept for this tab only.', 'unauthorized', p);
  }
  return new ApiError(401, 'Token refused',
    'The server refused the API token (401). Enter a valid token.', 'unauthorized', p);
}

function authHeaders(extra) {
  const h = new Headers(extra || {});
  const t = token();
  if (t) h.set('Authorization', `Bearer ${t}`);
  return h;
}

async function problemOf(resp) {
  let p = null;
  try {
    p = await resp.json();
  } catch {
    p = null;
  }
  if (resp.status === 401) return unauthorized(p);
  const title = (p && p.title) || resp.statusText || 'Request failed';
  const detail = (p && p.detail) || `HTTP ${resp.status}`;
  return new ApiError(resp.status, title, detail, p && p.code, p);
}

/** fetch with the token; throws ApiError. Returns the Response. */
export async function request(path, opts = {}) {
  let resp;
  try {
    resp = await fetch(path, { ...opts, headers: authHeaders(opts.headers) });
  } catch (e) {
    if (e && e.name === 'AbortError') throw e;
    throw unreachable();
  }
  if (!resp.ok && resp.status !== 206 && resp.status !== 304) throw await problemOf(resp);
  return resp;
}

/** A JSON call: GET by default; `body` is sent as JSON. Returns the parsed body (null for 204). */
export async function api(path, { method = 'GET', body, headers, signal } = {}) {
  const h = Object.assign({}, headers || {});
  if (body !== undefined) h['Content-Type'] = 'application/json';
  const resp = await request(path, {
    method, signal, headers: h, body: body === undefined ? undefined : JSON.stringify(body),
  });
  if (resp.status === 204) return null;
  return resp.json();
}

let limitsOnce = null;

/** The bounds the API checks at submission (`GET /v1/limits`), fetched once per page load. */
export function limits() {
  if (!limitsOnce) {
    limitsOnce = api('/v1/limits').catch((e) => {
      limitsOnce = null;
      throw e;
    });
  }
  return limitsOnce;
}

let protocolsOnce = null;

/**
 * The server's volume protocols (`GET /v1/protocols`: name, description, window, steps and products as
 * `POST /v1/jobs` takes them), the ones its processing rules run; fetched once per page load.
 */
export function protocols() {
  if (!protocolsOnce) {
    protocolsOnce = api('/v1/protocols').then((a) => a.protocols).catch((e) => {
      protocolsOnce = null;
      throw e;
    });
  }
  return protocolsOnce;
}

/** An ArrayBuffer, optionally a byte range [start, end] inclusive. */
export async function bytes(path, range, signal) {
  const headers = range ? { Range: `bytes=${range[0]}-${range[1]}` } : {};
  const resp = await request(path, { headers, signal });
  return resp.arrayBuffer();
}

/** An object URL of an authenticated image or file (revoke it when done). */
export async function blobUrl(path, signal) {
  const resp = await request(path, { signal });
  return URL.createObjectURL(await resp.blob());
}

/** Save an authenticated download under `name`. */
export async function download(path, name) {
  const url = await blobUrl(path);
  const a = document.createElement('a');
  a.href = url;
  a.download = name;
  document.body.append(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10000);
}

/**
 * Follow a stream of Server-Sent Events (a job's, or every job's at `/v1/events`): calls
 * onEvent(name, data, id) for each event until the stream ends or `signal` aborts. Resolves when the
 * stream ends. `lastEventId` resumes a stream after that event.
 */
export async function follow(path, onEvent, signal, lastEventId) {
  const headers = { Accept: 'text/event-stream' };
  if (lastEventId) headers['Last-Event-ID'] = lastEventId;
  const resp = await request(path, { signal, headers });
  const reader = resp.body.getReader();
  const dec = new TextDecoder();
  let buf = '';
  for (;;) {
    const { value, done } = await reader.read();
    if (done) break;
    buf += dec.decode(value, { stream: true }).replace(/\r\n?/g, '\n');
    let cut;
    while ((cut = buf.indexOf('\n\n')) >= 0) {
      const block = buf.slice(0, cut);
      buf = buf.slice(cut + 2);
      let name = 'message';
      let id = null;
      const data = [];
      for (const line of block.split('\n')) {
        if (line.startsWith('event:')) name = line.slice(6).trim();
        else if (line.startsWith('data:')) data.push(line.slice(5).replace(/^ /, ''));
        else if (line.startsWith('id:')) id = line.slice(3).trim();
      }
      if (data.length) {
        let parsed = null;
        try {
          parsed = JSON.parse(data.join('\n'));
        } catch {
          parsed = data.join('\n');
        }
        onEvent(name, parsed, id);
      }
    }
  }
}

/** POST a body with upload progress (XMLHttpRequest: fetch reports none). Resolves with the JSON answer. */
export function upload(path, body, contentType, onProgress) {
  return new Promise((resolve, reject) => {
    const x = new XMLHttpRequest();
    x.open('POST', path);
    const t = token();
    if (t) x.setRequestHeader('Authorization', `Bearer ${t}`);
    if (contentType) x.setRequestHeader('Content-Type', contentType);
    x.upload.onprogress = (e) => onProgress && onProgress(e.loaded, e.lengthComputable ? e.total : 0);
    x.onerror = () => reject(unreachable());
    x.onload = () => {
      let p = null;
      try {
        p = JSON.parse(x.responseText);
      } catch {
        p = null;
      }
      if (x.status >= 200 && x.status < 300) resolve(p);
      else if (x.status === 401) {
        reject(unauthorized(p));
      } else {
        reject(new ApiError(x.status, (p && p.title) || 'Upload failed',
          (p && p.detail) || `HTTP ${x.status}`, p && p.code, p));
      }
    };
    x.send(body);
  });
}
