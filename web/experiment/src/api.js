/**
 * The experiment server's HTTP API (docs/experiment.md), on the page's own origin.
 */

export class ApiError extends Error {
  constructor(message, status, data = null) {
    super(message);
    this.name = "ApiError";
    this.status = status;
    this.data = data;
    this.reason = data?.reason ?? null;
  }
}

const tokenKey = (participant) => `overhang-tower:token:${participant}`;

export function participantOf(params) {
  return params.PROLIFIC_PID || params.participant || null;
}

export function storedToken(participant) {
  try {
    return participant ? localStorage.getItem(tokenKey(participant)) : null;
  } catch {
    return null;
  }
}

export function storeToken(participant, token) {
  try {
    localStorage.setItem(tokenKey(participant), token);
  } catch {
    // Storage can be unavailable (private windows); the session then cannot be resumed.
  }
}

export async function post(path, body, token = null) {
  const headers = { "Content-Type": "application/json", Accept: "application/json" };
  if (token) headers.Authorization = `Bearer ${token}`;
  let response;
  try {
    response = await fetch(path, { method: "POST", headers, body: JSON.stringify(body) });
  } catch {
    throw new ApiError("The server could not be reached. Please check your connection and try again.", 0);
  }
  let data = null;
  try {
    data = await response.json();
  } catch {
    data = null;
  }
  if (!response.ok) {
    const message = data?.error ?? `The server answered ${response.status} ${response.statusText}.`;
    throw new ApiError(message, response.status, data);
  }
  return data;
}

/**
 * The page's URL parameters, without `token`: a token in the URL (a resume link the researcher
 * reissued) is stored for the participant and removed from the address bar, so it is neither
 * bookmarked nor shared with the screen.
 */
export function takeTokenFromUrl() {
  const url = new URL(window.location.href);
  const params = Object.fromEntries(url.searchParams);
  const { token, ...rest } = params;
  if (token) {
    const participant = participantOf(rest);
    if (participant) storeToken(participant, token);
    url.searchParams.delete("token");
    window.history.replaceState(window.history.state, "", url.pathname + url.search + url.hash);
  }
  return rest;
}

/** Starts or resumes the session of the participant named in the URL parameters. */
export async function openSession(params) {
  const participant = participantOf(params);
  const session = await post("api/sessions", { params }, storedToken(participant));
  storeToken(participant, session.token);
  return session;
}
