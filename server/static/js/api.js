// The study's JSON API, as the page uses it. Every request that changes something carries the
// participant's next sequence number; they are sent one at a time, in order, and a request whose
// answer was lost is sent again with the same number (the server answers it identically and
// stores it once).

export class ApiError extends Error {
  constructor(status, detail, headers = null) {
    super(detail || `HTTP ${status}`);
    this.status = status;
    this.detail = detail;
    this.headers = headers;
  }
}

const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));

// The participant's token when the server gave it to this page: sent in a header, since the
// cookie may be blocked (a cross-site iframe, as on Mechanical Turk). Kept in memory only.
let participantToken = null;

export function useParticipantToken(token) {
  participantToken = typeof token === "string" && token ? token : null;
}

function headersFor(body) {
  const headers = { Accept: "application/json" };
  if (body !== undefined) headers["Content-Type"] = "application/json";
  if (participantToken) headers["X-Participant-Token"] = participantToken;
  return headers;
}

/** An error answer's message: its detail, or the messages of a 422's list of problems. */
function describeError(data) {
  if (data && typeof data.detail === "string") return data.detail;
  if (data && Array.isArray(data.detail)) {
    const messages = data.detail.map((problem) => problem?.msg).filter((msg) => typeof msg === "string");
    if (messages.length) return messages.join("; ");
  }
  return null;
}

async function request(method, url, body) {
  const response = await fetch(url, {
    method,
    credentials: "same-origin",
    cache: "no-store",
    headers: headersFor(body),
    body: body === undefined ? undefined : JSON.stringify(body),
  });
  let data = null;
  try {
    data = await response.json();
  } catch {
    data = null;
  }
  if (!response.ok) {
    throw new ApiError(response.status, describeError(data) ?? response.statusText, response.headers);
  }
  return data;
}

/** A POST outside the participant's sequence (the experimenter's pages): the answer's JSON. */
export function postJSON(url, body) {
  return request("POST", url, body);
}

/** GET with retries while the connection is down (onRetry(attempt) is told). */
export async function getJSON(url, { onRetry } = {}) {
  for (let attempt = 1; ; attempt++) {
    try {
      return await request("GET", url);
    } catch (error) {
      if (!isTransient(error)) throw error;
      onRetry?.(attempt, error);
      await sleep(Math.min(500 * attempt, 5000));
    }
  }
}

function isTransient(error) {
  // fetch() rejects with a TypeError when the request did not get an answer.
  return error instanceof TypeError || (error instanceof ApiError && [502, 504].includes(error.status));
}

/**
 * Sends the requests that change something, one at a time, each with the next seq.
 * ``connection`` gets ``down(attempt)`` and ``up()`` calls for the page to show.
 */
export class Sequencer {
  constructor(nextSeq, connection = {}) {
    this.nextSeq = nextSeq;
    this.connection = connection;
    this.tail = Promise.resolve();
    this.pending = 0;
  }

  /**
   * Queue a POST. ``body`` (and ``url``) may be functions called when the request's turn comes;
   * a body of null skips the request (the page's state may have changed meanwhile).
   */
  post(url, body = {}) {
    this.pending += 1;
    const run = async () => {
      try {
        const payload = typeof body === "function" ? body() : body;
        if (payload === null) return null;
        return await this.send(typeof url === "function" ? url() : url, payload);
      } finally {
        this.pending -= 1;
      }
    };
    const result = this.tail.then(run, run);
    this.tail = result.catch(() => undefined);
    return result;
  }

  async send(url, payload) {
    const seq = this.nextSeq;
    for (let attempt = 1; ; attempt++) {
      try {
        const data = await request("POST", url, { ...payload, seq });
        if (attempt > 1) this.connection.up?.();
        this.nextSeq = data.participant.next_seq;
        return data;
      } catch (error) {
        if (isTransient(error)) {
          this.connection.down?.(attempt);
          await sleep(Math.min(500 * attempt, 5000));
          continue;
        }
        if (attempt > 1) this.connection.up?.();
        if (error instanceof ApiError && error.status === 409 && /sequence number|out of order/.test(error.detail)) {
          // Another tab (or a lost answer) moved the sequence on: learn where it is.
          const participant = await getJSON("/api/participant");
          this.nextSeq = participant.next_seq;
          error.resync = true;
        }
        throw error;
      }
    }
  }
}
