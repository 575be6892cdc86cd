// Open curve…: a drawing's file (SVG, DXF, CSV or JSON, as `links synthesize --curve` takes)
// read by the server (POST /api/curve), the one place drawings are parsed, into the points of
// the curve to synthesize for.

import { explain, limits, postJson } from "./api.js";

/** The curve in `file` ({points, closed} in the drawing's own units), `id` choosing an SVG
 * element or a DXF layer (else the first curve); rejects with the reason in words. */
export async function readCurveFile(file, id = "") {
  if (limits.max_body_bytes && file.size > limits.max_body_bytes) {
    throw new Error(
      `${file.name} is ${file.size.toLocaleString("en")} bytes: the server reads at most ` +
        `${limits.max_body_bytes.toLocaleString("en")}`,
    );
  }
  const text = await file.text();
  const answer = await postJson("/api/curve", { name: file.name, text, ...(id ? { id } : {}) });
  if (answer.status !== 200 || !answer.data || !Array.isArray(answer.data.points)) {
    throw new Error(explain(answer));
  }
  return answer.data;
}
