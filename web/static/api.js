// The page's client of qemd's /v1 API: the bearer token (kept in sessionStorage, i.e. for this
// browser tab only) and fetch helpers that turn RFC 9457 problems into errors carrying the
// server's own text.

const KEY = 'qemd.token';

export function token() { return sessionStorage.getItem(KEY) || ''; }
export function setToken(t) { if (t) sessionStorage.setItem(KEY, t); else sessionStorage.removeItem(KEY); }

export function authHeaders(extra = {}) {
  const t = token();
  return t ? { ...extra, Authorization: `Bearer ${t}` } : { ...extra };
}

/** An error answered by the server: status, the problem's detail and field. */
export class ApiProblem extends Error {
  constructor(status, problem) {
    super(problem.detail || problem.title || `HTTP ${status}`);
    this.status = status;
    this.field = problem.field || null;
    this.problem = problem;
  }
}

async function problemOf(r) {
  try { return await r.json(); } catch { return { detail: `${r.status} ${r.statusText}` }; }
}

/** fetch with the token; JSON in, JSON out; throws ApiProblem on an error status. */
export async function api(path, { method = 'GET', body, headers = {} } = {}) {
  const init = { method, headers: authHeaders(headers) };
  if (body !== undefined) {
    init.body = JSON.stringify(body);
    init.headers['Content-Type'] = 'application/json';
  }
  const r = await fetch(path, init);
  if (!r.ok) throw new ApiProblem(r.status, await problemOf(r));
  if (r.status === 204) return null;
  return r.json();
}

/** GET returning an ArrayBuffer (previews). */
export async function binary(path) {
  const r = await fetch(path, { headers: authHeaders() });
  if (!r.ok) throw new ApiProblem(r.status, await problemOf(r));
  return r.arrayBuffer();
}

/** Downloads a result through fetch (the token is a header, so a plain link cannot carry it). */
export async function download(path, filename) {
  const r = await fetch(path, { headers: authHeaders() });
  if (!r.ok) throw new ApiProblem(r.status, await problemOf(r));
  const url = URL.createObjectURL(await r.blob());
  const a = document.createElement('a');
  a.href = url;
  a.download = filename;
  document.body.append(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 60_000);
}
