// The 3D scene of a kit, drawn with three.js: each link a flat bar with a hole at each joint,
// on its layer; each pin a rod through its span of layers; the spacers on the pins; the base
// plate under them. Everything is built from the bill of materials of POST /api/kit.
//
// The scene's frame is the kit's own (millimetres, z up), so a part's world position is where
// the bill and the joints' positions put it, moved up only by the explode spacing: each layer
// l rises by l times the spacing (the base plate, layer -1, sinks by one), and a pin or spacer
// stretches between the layers at its two ends. Loaded only when a kit is first shown: three.js
// is 2 MB.

import * as THREE from "./vendor/three-0.187.0/three.module.js";
import { Orbit } from "./orbit.js";

const FOV_DEG = 40;
const CURVE_SEGMENTS = 24; // per rounded end or hole: smooth enough at any zoom a kit is seen
const COLORS = {
  crank: 0xd9480f, // as the editor draws the crank
  pin: 0x8a939e,
  spacer: 0xd6b656,
  base: 0xc3cad4,
  background: 0xfbfcfe,
};

/** A bar's outline: `length` between its hole centres along +x from the origin, `width` across,
 * its ends rounded about the holes, and the two holes. */
function barShape(length, width, hole) {
  const r = width / 2;
  const shape = new THREE.Shape();
  shape.moveTo(0, -r);
  shape.lineTo(length, -r);
  shape.absarc(length, 0, r, -Math.PI / 2, Math.PI / 2, false);
  shape.lineTo(0, r);
  shape.absarc(0, 0, r, Math.PI / 2, (3 * Math.PI) / 2, false);
  shape.holes.push(circle(0, 0, hole / 2), circle(length, 0, hole / 2));
  return shape;
}

function circle(x, y, radius) {
  const path = new THREE.Path();
  path.absarc(x, y, radius, 0, 2 * Math.PI, true);
  return path;
}

/** An extruded outline from z = 0 up to z = `depth`. */
function slab(shape, depth) {
  return new THREE.ExtrudeGeometry(shape, {
    depth,
    bevelEnabled: false,
    curveSegments: CURVE_SEGMENTS,
  });
}

/** A rod or tube 1 mm tall standing on the origin: its mesh's scale.z makes its length, which
 * the explode spacing changes. */
function unitTube(outer, inner = 0) {
  const shape = new THREE.Shape();
  shape.absarc(0, 0, outer / 2, 0, 2 * Math.PI, false);
  if (inner > 0) shape.holes.push(circle(0, 0, inner / 2));
  return slab(shape, 1);
}

/** Each layer its own colour, so that the stacking reads at a glance. */
function layerColor(layer) {
  return new THREE.Color().setHSL(((layer * 137.508 + 200) % 360) / 360, 0.55, 0.55);
}

export class KitScene {
  /** Draw on `canvas`; throws if the browser has no WebGL. */
  constructor(canvas) {
    this.canvas = canvas;
    this.renderer = new THREE.WebGLRenderer({ canvas, antialias: true });
    this.renderer.setPixelRatio(window.devicePixelRatio || 1);
    this.renderer.setClearColor(COLORS.background);
    this.scene = new THREE.Scene();
    this.camera = new THREE.PerspectiveCamera(FOV_DEG, 1, 0.1, 1e7);
    this.camera.up.set(0, 0, 1); // the kit's z is up
    this.scene.add(new THREE.HemisphereLight(0xffffff, 0x8090a0, 1.6));
    const sun = new THREE.DirectionalLight(0xffffff, 1.8);
    sun.position.set(-0.4, -0.6, 1); // from above and in front: the bars' tops and sides differ
    this.scene.add(sun);
    this.kit = new THREE.Group();
    this.scene.add(this.kit);
    this.orbit = new Orbit(canvas, () => this.requestRender());
    this.pending = false;
    new ResizeObserver(() => this.resize()).observe(canvas);
  }

  resize() {
    const { clientWidth: width, clientHeight: height } = this.canvas;
    if (!width || !height) return;
    this.renderer.setSize(width, height, false); // the style sheet sizes the canvas
    this.camera.aspect = width / height;
    this.camera.updateProjectionMatrix();
    this.requestRender();
  }

  /** Replace the parts with those of `bom` (POST /api/kit's bill of materials). */
  setKit(bom) {
    this.clear();
    const T = bom.layer_thickness_mm;
    for (const link of bom.links) {
      const color = link.kind === "crank" ? COLORS.crank : layerColor(link.layer);
      const shape = barShape(link.length_mm, bom.bar_width_mm, bom.hole_diameter_mm);
      this.add(slab(shape, T), color, { kind: "link", name: link.node, link });
    }
    for (const pin of bom.pins) {
      const metal = { metalness: 0.6, roughness: 0.4 };
      this.add(unitTube(pin.diameter_mm), COLORS.pin, { kind: "pin", name: pin.node, pin }, metal);
    }
    for (const spacer of bom.spacers) {
      const tube = unitTube(spacer.outer_diameter_mm, spacer.inner_diameter_mm);
      this.add(tube, COLORS.spacer, { kind: "spacer", name: spacer.node, spacer });
    }
    if (bom.base) {
      const [x0, y0, x1, y1] = bom.base.extent_mm;
      const plate = new THREE.Shape();
      plate.moveTo(x0, y0);
      plate.lineTo(x1, y0);
      plate.lineTo(x1, y1);
      plate.lineTo(x0, y1);
      plate.closePath();
      for (const post of bom.base.posts) {
        const joint = bom.joints.find((j) => j.joint === post);
        plate.holes.push(circle(joint.x_mm, joint.y_mm, bom.base.hole_diameter_mm / 2));
      }
      const depth = bom.base.z_mm[1] - bom.base.z_mm[0];
      this.add(slab(plate, depth), COLORS.base, {
        kind: "base",
        name: bom.base.node,
        base: bom.base,
      });
    }
  }

  add(geometry, color, data, finish = { metalness: 0.05, roughness: 0.7 }) {
    const material = new THREE.MeshStandardMaterial({ color, ...finish });
    const mesh = new THREE.Mesh(geometry, material);
    mesh.name = data.name;
    mesh.userData = data;
    this.kit.add(mesh);
  }

  clear() {
    for (const mesh of [...this.kit.children]) {
      mesh.geometry.dispose();
      mesh.material.dispose();
      this.kit.remove(mesh);
    }
  }

  /** Place every part with the joints at `joints` ([x, y] in mm, by joint) and the layers
   * `explode` mm further apart each: a bar at its lower joint, turned towards its upper one. */
  pose(joints, explode) {
    const lift = (z, layer) => z + explode * layer;
    for (const mesh of this.kit.children) {
      const { kind, link, pin, spacer, base } = mesh.userData;
      if (kind === "link") {
        const [i, j] = link.joints;
        const [x, y] = joints[i];
        mesh.position.set(x, y, lift(link.z_mm[0], link.layer));
        mesh.rotation.z = Math.atan2(joints[j][1] - y, joints[j][0] - x);
      } else if (kind === "base") {
        mesh.position.set(0, 0, lift(base.z_mm[0], -1));
      } else {
        // A pin's ends lie in the gaps by its lowest and highest links (a post's in the
        // plate); a spacer's on the layers it separates.
        const [below, above] = pin
          ? [pin.post ? -1 : pin.layers[0], pin.layers[1]]
          : spacer.between;
        const part = pin || spacer;
        const bottom = lift(part.z_mm[0], below);
        const [x, y] = joints[part.joint];
        mesh.position.set(x, y, bottom);
        mesh.scale.z = lift(part.z_mm[1], above) - bottom;
      }
    }
    this.requestRender();
  }

  /** Look at the kit whole: `box` {min: [x, y, z], max: [x, y, z]} in mm. */
  frame(box) {
    const centre = box.min.map((low, k) => (low + box.max[k]) / 2);
    const radius = Math.hypot(...box.max.map((high, k) => high - box.min[k])) / 2;
    this.orbit.frame(centre, Math.max(radius, 1), FOV_DEG);
  }

  requestRender() {
    if (this.pending) return;
    this.pending = true;
    requestAnimationFrame(() => {
      this.pending = false;
      this.render();
    });
  }

  render() {
    this.camera.position.set(...this.orbit.eye());
    this.camera.near = this.orbit.distance / 1000;
    this.camera.far = this.orbit.distance * 100;
    this.camera.updateProjectionMatrix();
    this.camera.lookAt(...this.orbit.target);
    this.renderer.render(this.scene, this.camera);
    this.canvas.dataset.rendered = String(this.renderer.info.render.calls);
  }

  /** Every part as drawn: its kind, its node's name, its layer (or [below, above] layers),
   * the world position of its own origin (a bar's lower joint; a pin's or spacer's foot)
   * and, for a bar, the world positions of its two hole centres; in mm, z up. */
  parts() {
    this.kit.updateMatrixWorld(true);
    const world = (mesh, x, y, z) =>
      new THREE.Vector3(x, y, z).applyMatrix4(mesh.matrixWorld).toArray();
    return this.kit.children.map((mesh) => {
      const { kind, name, link, pin, spacer } = mesh.userData;
      const found = { kind, name, position: world(mesh, 0, 0, 0) };
      if (link) {
        found.layer = link.layer;
        found.ends = [found.position, world(mesh, link.length_mm, 0, 0)];
      } else if (pin) {
        found.layers = pin.layers;
      } else if (spacer) {
        found.layers = spacer.between;
      } else {
        found.layer = -1;
      }
      return found;
    });
  }

  /** What the last frame drew: its draw calls (one a part in view) and triangles. */
  drawn() {
    const { calls, triangles } = this.renderer.info.render;
    return { calls, triangles };
  }
}
