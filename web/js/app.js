// The viewer's entry: the token form, the server check, and hash routes
// (#/jobs, #/job/{id}, #/send, #/series/{id}).

import { api, setToken, token, ApiError } from './api.js';
import { banner, clear, errorBox, h } from './dom.js';
import { showJobs } from './jobs.js';
import { showJob } from './job.js';
import { showSend, showSeries } from './send.js';

const main = document.getElementById('main');
let current = null; // AbortController of the page shown

/** Check the server answers and the token is accepted; shows the banner otherwise. */
async function check() {
  try {
    await fetch('/healthz', { cache: 'no-store' });
  } catch {
    throw new ApiError(0, 'Server unreachable',
      `The ctrecon server at ${location.origin} does not answer. Is it running?`, 'unreachable');
  }
  await api('/v1/jobs?limit=1&fields=id');
}

async function route() {
  if (current) current.abort();
  current = new AbortController();
  const signal = current.signal;
  const hash = location.hash || '#/jobs';
  const [, page, id] = hash.split('?')[0].split('/');
  for (const a of document.querySelectorAll('header nav a')) {
    a.toggleAttribute('aria-current', a.getAttribute('href') === `#/${page}`);
  }
  clear(main);
  try {
    await check();
    banner(null);
  } catch (e) {
    if (e.name === 'AbortError') return;
    banner(e);
    main.append(h('section.panel#page-error', h('h1', e.status === 401 ? 'Token needed' : 'Cannot load'),
      errorBox(e), h('p', e.status === 401
        ? 'Enter the API token above; it is kept for this tab only (sessionStorage).'
        : 'Start the server (ctrecon serve) and reload this page.')));
    if (e.status === 401) document.getElementById('token-input').focus();
    return;
  }
  try {
    if (page === 'job' && id) await showJob(main, id, signal);
    else if (page === 'send') await showSend(main, signal);
    else if (page === 'series' && id) await showSeries(main, id, signal);
    else await showJobs(main, signal);
  } catch (e) {
    if (e.name === 'AbortError') return;
    main.append(errorBox(e));
    if (e.status === 0 || e.status === 401) banner(e);
  }
}

document.getElementById('token-form').addEventListener('submit', (ev) => {
  ev.preventDefault();
  const input = document.getElementById('token-input');
  setToken(input.value.trim());
  input.value = '';
  input.placeholder = token() ? 'token set for this tab' : 'bearer token (if the server needs one)';
  route();
});
document.getElementById('token-forget').addEventListener('click', () => {
  setToken('');
  document.getElementById('token-input').placeholder = 'bearer token (if the server needs one)';
  route();
});
if (token()) document.getElementById('token-input').placeholder = 'token set for this tab';
window.addEventListener('hashchange', route);
route();
