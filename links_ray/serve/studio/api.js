// Talking to the links-ray HTTP API (docs/reference/contract.md, HTTP API). Every failure becomes a
// sentence the page can show: the server's own `error` message when it sent one.

/** POST a JSON body; resolves to {status, data, ms} for any HTTP answer, rejects on no answer. */
export async function postJson(path, body) {
  const started = performance.now();
  const response = await send(path, {
    method: "POST",
    headers: { "Content-Type": "application/json" },
    body: JSON.stringify(body),
  });
  const data = await readJson(response);
  return { status: response.status, data, ms: performance.now() - started };
}

/**
 * POST a JSON body whose 200 answer is NDJSON (a streamed synthesis): calls `onLine` with each
 * line's JSON as it arrives, and resolves to {status, data, ms} with the last line as `data`
 * (or, for any other answer, the server's JSON as postJson has it).
 */
export async function postJsonLines(path, body, onLine) {
  const started = performance.now();
  const response = await send(path, {
    method: "POST",
    headers: { "Content-Type": "application/json" },
    body: JSON.stringify(body),
  });
  const type = response.headers.get("Content-Type") || "";
  if (response.status !== 200 || !type.startsWith("application/x-ndjson") || !response.body) {
    return { status: response.status, data: await readJson(response), ms: 0 };
  }
  const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
  let pending = "";
  let last = null;
  for (;;) {
    const { value, done } = await reader.read();
    if (value) pending += value;
    const lines = pending.split("\n");
    pending = done ? "" : lines.pop();
    for (const line of lines) {
      if (!line.trim()) continue;
      last = JSON.parse(line);
      onLine(last);
    }
    if (done) break;
  }
  return { status: response.status, data: last, ms: performance.now() - started };
}

/**
 * POST a JSON body for a file to download; resolves to {status, blob, name, type} on 200 (the
 * file's bytes, the name its Content-Disposition gives, its type), else {status, data} with
 * the server's JSON as postJson has it. A Blob, not text: a GLB or a zip is binary.
 */
export async function postForFile(path, body, fallbackName) {
  const response = await send(path, {
    method: "POST",
    headers: { "Content-Type": "application/json" },
    body: JSON.stringify(body),
  });
  if (response.status !== 200) return { status: response.status, data: await readJson(response) };
  const disposition = response.headers.get("Content-Disposition") || "";
  const named = /filename="([^"]+)"/.exec(disposition);
  return {
    status: 200,
    blob: await response.blob(),
    name: named ? named[1] : fallbackName,
    type: response.headers.get("Content-Type") || "application/octet-stream",
  };
}

/** GET a JSON document; as postJson. */
export async function getJson(path) {
  const started = performance.now();
  const response = await send(path, {});
  const data = await readJson(response);
  return { status: response.status, data, ms: performance.now() - started };
}

async function send(path, options) {
  try {
    return await fetch(path, options);
  } catch (err) {
    throw new Error(`cannot reach the links-ray server (${err.message})`);
  }
}

async function readJson(response) {
  const text = await response.text();
  try {
    return text ? JSON.parse(text) : null;
  } catch {
    return null; // not JSON: `explain` says so with the status
  }
}

/**
 * The limits every request meets, as the API gives them (GET /api/limits: max_points, max_k,
 * max_joints, max_transmission_deg, ...). Empty until `loadLimits` has read them; checks that
 * find a limit missing leave the refusal to the server.
 */
export const limits = {};

/** Read the API's limits into `limits`; rejects with the reason if the API does not answer. */
export async function loadLimits() {
  const answer = await getJson("/api/limits");
  if (answer.status !== 200 || !answer.data || typeof answer.data !== "object") {
    throw new Error(explain(answer));
  }
  Object.assign(limits, answer.data);
  return limits;
}

/** The words for an answer that is not a success. */
export function explain(answer) {
  const message = answer.data && typeof answer.data.error === "string" ? answer.data.error : "";
  if (message) return `${message} (HTTP ${answer.status})`;
  return answer.status === 200
    ? "the server's answer was not the JSON expected"
    : `the server answered HTTP ${answer.status} without an explanation`;
}

/**
 * Runs jobs one at a time, keeping only the newest waiting job. While a request is in flight,
 * newer jobs replace each other; when it returns, the latest one is sent. A drag then lags by
 * at most one round trip and never builds a queue of stale requests.
 */
export class Latest {
  constructor(run) {
    this.run = run; // async (job) => void; must handle its own errors
    this.waiting = null;
    this.busy = false;
  }

  push(job) {
    this.waiting = job;
    if (!this.busy) this.next();
  }

  get idle() {
    return !this.busy && this.waiting === null;
  }

  async next() {
    const job = this.waiting;
    this.waiting = null;
    if (job === null) return;
    this.busy = true;
    try {
      await this.run(job);
    } finally {
      this.busy = false;
      if (this.waiting !== null) this.next();
    }
  }
}
