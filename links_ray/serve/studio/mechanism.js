// The mechanism model of docs/reference/contract.md, Mechanisms (adjacency, node_types, positions) and the
// edits the editor makes to it. Edits return a new mechanism and never change their input, so
// the undo history can keep plain snapshots.

export const FIXED = 0;
export const SIMPLE = 1;
export const ACTUATED = 2;
import { limits } from "./api.js";

/** The crank (joint 0 fixed at the dataset's pivot, joint 1 its tip) and one ground joint. */
export function starter() {
  return {
    adjacency: [
      [0, 1, 0],
      [1, 0, 0],
      [0, 0, 0],
    ],
    node_types: [FIXED, ACTUATED, FIXED],
    positions: [
      [0.5, 0.5],
      [0.55, 0.5],
      [0.8, 0.5],
    ],
  };
}

/**
 * What the studio opens on: a crank-rocker four-bar whose coupler plate carries joint 4.
 * Crank 0-1 0.05 (the dataset's crank), coupler 1-3 0.13, rocker 2-3 0.09, ground 0-2 0.15:
 * Grashof (0.05 + 0.15 < 0.13 + 0.09) with the crank shortest and grounded, so the crank turns
 * fully while the rocker swings 67 degrees. The transmission angle at joint 3 stays within
 * 50-130 degrees; the plate 1-3-4 is isosceles, 53 degrees at joint 4.
 */
export function opening() {
  return {
    adjacency: [
      [0, 1, 0, 0, 0],
      [1, 0, 0, 1, 1],
      [0, 0, 0, 1, 0],
      [0, 1, 1, 0, 1],
      [0, 1, 0, 1, 0],
    ],
    node_types: [FIXED, ACTUATED, FIXED, SIMPLE, SIMPLE],
    positions: [
      [0.5, 0.5],
      [0.55, 0.5],
      [0.65, 0.5],
      [0.644, 0.5898],
      [0.5072, 0.6389],
    ],
  };
}

export function clone(mech) {
  return {
    adjacency: mech.adjacency.map((row) => row.slice()),
    node_types: mech.node_types.slice(),
    positions: mech.positions.map((p) => p.slice()),
  };
}

export function jointCount(mech) {
  return mech.node_types.length;
}

/** Every link as [i, j] with i < j. */
export function links(mech) {
  const found = [];
  const n = jointCount(mech);
  for (let i = 0; i < n; i++) {
    for (let j = i + 1; j < n; j++) if (mech.adjacency[i][j]) found.push([i, j]);
  }
  return found;
}

/** A key that changes exactly when the topology does (not when joints move). */
export function topologyKey(mech) {
  return JSON.stringify([mech.adjacency, mech.node_types]);
}

function checkRoom(mech) {
  // The most joints one request may carry: the API's limit (undefined until read: no check).
  if (jointCount(mech) >= limits.max_joints) {
    throw new Error(`a mechanism can have at most ${limits.max_joints} joints`);
  }
}

function withJoint(mech, kind, point) {
  checkRoom(mech);
  const next = clone(mech);
  next.adjacency.forEach((row) => row.push(0));
  next.adjacency.push(new Array(jointCount(next) + 1).fill(0));
  next.node_types.push(kind);
  next.positions.push([point[0], point[1]]);
  return next;
}

/** The J-operator: a new simple joint at `point`, linked to joints a and b. */
export function addJoint(mech, a, b, point) {
  if (a === b) throw new Error("pick two different joints");
  const next = withJoint(mech, SIMPLE, point);
  const j = jointCount(next) - 1;
  for (const parent of [a, b]) {
    next.adjacency[j][parent] = 1;
    next.adjacency[parent][j] = 1;
  }
  return next;
}

/** A new fixed joint at `point`, linked to nothing yet. */
export function addGround(mech, point) {
  return withJoint(mech, FIXED, point);
}

/** Add the link a-b, or remove it if it is there. The crank link (0, 1) stays. */
export function toggleLink(mech, a, b) {
  if (a === b) throw new Error("a link needs two different joints");
  const next = clone(mech);
  const value = next.adjacency[a][b] ? 0 : 1;
  if (!value && isCrank(a, b)) throw new Error("the crank link (0, 1) cannot be removed");
  next.adjacency[a][b] = value;
  next.adjacency[b][a] = value;
  return next;
}

export function isCrank(a, b) {
  return Math.min(a, b) === 0 && Math.max(a, b) === 1;
}

/** Remove joint j and its links; later joints move down one index. Joints 0 and 1 stay. */
export function removeJoint(mech, j) {
  if (j < 2) throw new Error("joints 0 and 1 are the crank and cannot be deleted");
  const keep = (_, i) => i !== j;
  return {
    adjacency: mech.adjacency.filter(keep).map((row) => row.filter(keep)),
    node_types: mech.node_types.filter(keep),
    positions: mech.positions.filter(keep).map((p) => p.slice()),
  };
}

export function moveJoint(mech, j, point) {
  const next = clone(mech);
  next.positions[j] = [point[0], point[1]];
  return next;
}

function isFiniteNumber(value) {
  return typeof value === "number" && Number.isFinite(value);
}

/**
 * A mechanism from parsed JSON: the fields of docs/reference/contract.md, Mechanisms, or a retrieval
 * result holding them under "mechanism". Throws an Error that says what is wrong. The server
 * checks the rest (joint types, symmetry, solvability) and the studio shows what it says.
 */
export function parseMechanism(value) {
  if (value && typeof value === "object" && !Array.isArray(value) && value.mechanism) {
    value = value.mechanism;
  }
  if (!value || typeof value !== "object" || Array.isArray(value)) {
    throw new Error("expected a JSON object with adjacency, node_types and positions");
  }
  for (const field of ["adjacency", "node_types", "positions"]) {
    if (!(field in value)) throw new Error(`the field "${field}" is missing`);
    if (!Array.isArray(value[field])) throw new Error(`"${field}" must be an array`);
  }
  const { adjacency, node_types: types, positions } = value;
  const n = types.length;
  if (n < 2) throw new Error(`a mechanism needs at least the 2 crank joints, got ${n}`);
  if (n > limits.max_joints) throw new Error(`at most ${limits.max_joints} joints, got ${n}`);
  if (adjacency.length !== n || positions.length !== n) {
    throw new Error(
      `adjacency has ${adjacency.length} rows and positions ${positions.length} pairs, ` +
        `but node_types has ${n} joints`,
    );
  }
  adjacency.forEach((row, i) => {
    if (!Array.isArray(row) || row.length !== n) {
      throw new Error(`adjacency row ${i} must hold ${n} entries`);
    }
    row.forEach((entry, j) => {
      if (entry !== 0 && entry !== 1) throw new Error(`adjacency[${i}][${j}] must be 0 or 1`);
    });
  });
  types.forEach((kind, i) => {
    if (![FIXED, SIMPLE, ACTUATED].includes(kind)) {
      throw new Error(`node_types[${i}] must be 0 (fixed), 1 (simple) or 2 (actuated)`);
    }
  });
  positions.forEach((p, i) => {
    if (!Array.isArray(p) || p.length !== 2 || !p.every(isFiniteNumber)) {
      throw new Error(`positions[${i}] must be an [x, y] pair of finite numbers`);
    }
  });
  return clone({ adjacency, node_types: types, positions });
}
