// The service's HTTP API, as the console calls it: relative to the page (served at /ui/), with
// the API key the user entered sent as "Authorization: Bearer <key>", as every client sends it.
// An error answer becomes an ApiError carrying the service's status and detail.

const KEY = "dpc-mn-api-key"; // sessionStorage: forgotten when the tab closes

export class ApiError extends Error {
  constructor(status, detail) {
    super(`${status}: ${detail}`);
    this.status = status;
    this.detail = detail;
  }
}

export function apiKey() {
  return sessionStorage.getItem(KEY) || "";
}

export function setApiKey(key) {
  if (key) sessionStorage.setItem(KEY, key);
  else sessionStorage.removeItem(KEY);
}

// fetch(route) with the key; params: {name: value | [values]}, null and "" left out.
export async function call(method, route, { body, headers, params } = {}) {
  const url = new URL(`../${route}`, document.baseURI);
  for (const [name, value] of Object.entries(params || {})) {
    for (const item of [].concat(value ?? [])) {
      if (item !== "") url.searchParams.append(name, item);
    }
  }
  const sent = new Headers(headers || {});
  if (apiKey()) sent.set("Authorization", `Bearer ${apiKey()}`);
  const response = await fetch(url, { method, body, headers: sent });
  if (!response.ok) {
    let detail = response.statusText;
    try {
      detail = (await response.json()).detail ?? detail;
    } catch {
      // not JSON: keep the status text
    }
    throw new ApiError(response.status, detail);
  }
  return response;
}

export async function json(method, route, options) {
  return (await call(method, route, options)).json();
}

// Raw little-endian float32 x y z triples (the browser's own byte order: little-endian on
// every platform a browser runs on), and the answer's headers.
export async function floats(method, route, options) {
  const response = await call(method, route, options);
  return { points: new Float32Array(await response.arrayBuffer()), headers: response.headers };
}
