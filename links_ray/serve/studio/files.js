// Saving and sharing: JSON and SVG downloads, reading an imported file, share links.

import { FIXED, isCrank, links, parseMechanism } from "./mechanism.js";
import { bounds, jointColor } from "./view.js";

/** Offer `content` (text or a Blob) as a file download named `name`. */
export function download(name, content, type) {
  const url = URL.createObjectURL(new Blob([content], { type }));
  const anchor = document.createElement("a");
  anchor.href = url;
  anchor.download = name;
  document.body.append(anchor);
  anchor.click();
  anchor.remove();
  // The browser has taken its copy once the click is handled; free ours a little later.
  setTimeout(() => URL.revokeObjectURL(url), 10_000);
}

/** The mechanism fields (docs/reference/contract.md, Mechanisms) as JSON text. */
export function mechanismJson(mech) {
  const { adjacency, node_types, positions } = mech;
  return JSON.stringify({ adjacency, node_types, positions }, null, 1);
}

/** A mechanism from a JSON file the user picked; rejects with the reason in words. */
export async function readMechanismFile(file) {
  const text = await file.text();
  let value;
  try {
    value = JSON.parse(text);
  } catch (err) {
    throw new Error(`${file.name} is not valid JSON (${err.message})`);
  }
  try {
    return parseMechanism(value);
  } catch (err) {
    throw new Error(`${file.name} is not a mechanism: ${err.message}`);
  }
}

function fmt(value) {
  return Number(value.toFixed(2));
}

/**
 * An SVG drawing of the mechanism in its starting pose with every moving joint's path,
 * y up as in the editor. `trajectories` may be null (nothing simulated) or cut short by a lock.
 */
export function mechanismSvg(mech, trajectories, lock = null) {
  const width = 800;
  const b = bounds(mech.positions, ...(trajectories || []));
  const extent = Math.max(b.maxX - b.minX, b.maxY - b.minY, 1e-6);
  const scale = (width * 0.9) / extent;
  const height = Math.max(200, Math.round((b.maxY - b.minY) * scale + width * 0.1));
  const toSvg = (p) => [
    fmt(width / 2 + (p[0] - (b.minX + b.maxX) / 2) * scale),
    fmt(height / 2 - (p[1] - (b.minY + b.maxY) / 2) * scale),
  ];
  const parts = [
    `<svg xmlns="http://www.w3.org/2000/svg" width="${width}" height="${height}" ` +
      `viewBox="0 0 ${width} ${height}">`,
    `<title>links-ray mechanism: ${mech.node_types.length} joints` +
      `${lock ? `, locks at ${lock.angle.toFixed(1)} degrees` : ""}</title>`,
    `<rect width="${width}" height="${height}" fill="#ffffff"/>`,
  ];
  (trajectories || []).forEach((path, j) => {
    if (mech.node_types[j] === FIXED || path.length < 2) return;
    const points = path.map((p) => toSvg(p).join(",")).join(" ");
    const tag = lock ? "polyline" : "polygon";
    parts.push(
      `<${tag} class="path" data-joint="${j}" points="${points}" fill="none" ` +
        `stroke="${jointColor(j)}" stroke-width="1.5"/>`,
    );
  });
  for (const [i, j] of links(mech)) {
    const [x1, y1] = toSvg(mech.positions[i]);
    const [x2, y2] = toSvg(mech.positions[j]);
    const stroke = isCrank(i, j) ? "#d9480f" : "#3b4452";
    parts.push(
      `<line class="link" x1="${x1}" y1="${y1}" x2="${x2}" y2="${y2}" stroke="${stroke}" ` +
        `stroke-width="4" stroke-linecap="round"/>`,
    );
  }
  mech.positions.forEach((p, j) => {
    const [x, y] = toSvg(p);
    const fill = mech.node_types[j] === FIXED ? "#3b4452" : "#ffffff";
    parts.push(
      `<circle class="joint" data-joint="${j}" data-type="${mech.node_types[j]}" cx="${x}" ` +
        `cy="${y}" r="6" fill="${fill}" stroke="#3b4452" stroke-width="2"/>`,
    );
  });
  parts.push("</svg>");
  return parts.join("\n");
}

// Share links carry the mechanism in the address's fragment, so it never reaches a server log.
const SHARE_KEY = "#mechanism=";

export function shareUrl(mech) {
  const text = JSON.stringify({
    adjacency: mech.adjacency,
    node_types: mech.node_types,
    positions: mech.positions,
  });
  return location.origin + location.pathname + SHARE_KEY + encodeURIComponent(text);
}

/** The mechanism in the page address, null if there is none; throws if it is unreadable. */
export function sharedMechanism() {
  if (!location.hash.startsWith(SHARE_KEY)) return null;
  let value;
  try {
    value = JSON.parse(decodeURIComponent(location.hash.slice(SHARE_KEY.length)));
  } catch {
    throw new Error("the mechanism in the page address is not readable JSON");
  }
  return parseMechanism(value);
}
