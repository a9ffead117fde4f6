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
    this.contact = data?.contact ?? null;
    // worth trying again: no answer, the server's own failure, a database that is away for a moment
    this.retryable = status === 0 || status >= 500 || status === 429;
  }
}

/** What a participant is told of an answer that is not the server's JSON (a proxy's page, say). */
function wordsFor(status) {
  if (status === 413) return "The page sent more than the study's server takes. Please reload the page.";
  if (status >= 500) {
    return `The study's server did not answer properly (error ${status}). Please wait a moment and try again.`;
  }
  return `The study's server could not take this step (error ${status}). Please reload the page.`;
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
    // the server's JSON says it in the participant's words (message); anything else gets words here
    const message = data?.message ?? wordsFor(response.status);
    throw new ApiError(message, response.status, data);
  }
  return data;
}

/**
 * The page's URL parameters and, apart, a `token` from the URL (a resume link the researcher
 * reissued), which is removed from the address bar so that it is neither bookmarked nor shown.
 */
export function takeTokenFromUrl() {
  const url = new URL(window.location.href);
  const { token = null, ...params } = Object.fromEntries(url.searchParams);
  if (token) {
    url.searchParams.delete("token");
    window.history.replaceState(window.history.state, "", url.pathname + url.search + url.hash);
  }
  return { params, token };
}

/**
 * Starts or resumes the session of the participant named in the URL parameters, with the link's
 * token when there is one (else the one this browser keeps). A link's token replaces the kept one
 * only once the server accepted it: an old, revoked link does not undo a newer one.
 */
export async function openSession(params, linkToken = null) {
  const participant = participantOf(params);
  const kept = storedToken(participant);
  let session;
  try {
    session = await post("api/sessions", { params }, linkToken ?? kept);
  } catch (error) {
    if (!(linkToken && kept && kept !== linkToken && error.status === 403)) throw error;
    session = await post("api/sessions", { params }, kept);
  }
  storeToken(participant, session.token);
  return session;
}
