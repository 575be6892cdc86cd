// Turning the 3D view by hand: drag to orbit around what is shown, wheel or pinch to zoom,
// shift-drag or the right button to pan. Written by hand rather than taken from three.js's
// addons: theirs import the bare name "three", which a page can only resolve with an inline
// import map, and the studio's CSP forbids inline scripts. It knows nothing of three.js; the
// scene asks it where the eye is. The frame is the kit's, z up.

const TURN_PER_PIXEL = 0.008; // radians of turn per pixel dragged
const ZOOM_PER_WHEEL = 0.0015; // wheel deltaY to a zoom factor, as an exponent
const LIMIT = Math.PI / 2 - 0.01; // never straight overhead or under: "up" would be undefined

export class Orbit {
  /** Listen on `element`; `onChange()` after every move of the eye. */
  constructor(element, onChange) {
    this.element = element;
    this.onChange = onChange;
    this.target = [0, 0, 0];
    this.azimuth = -Math.PI / 3; // the eye's direction from the target, from +x, seen from above
    this.elevation = 0.45; // low enough that the layers stand apart, high enough to see in
    this.distance = 100;
    this.pointers = new Map(); // pointer id -> [x, y]: one drags, two pinch
    this.pinch = 0;
    element.addEventListener("pointerdown", (e) => this.down(e));
    element.addEventListener("pointermove", (e) => this.move(e));
    element.addEventListener("pointerup", (e) => this.up(e));
    element.addEventListener("pointercancel", (e) => this.up(e));
    element.addEventListener("contextmenu", (e) => e.preventDefault()); // the right button pans
    element.addEventListener("wheel", (e) => this.wheel(e), { passive: false });
  }

  /** Look at `centre` from about where a sphere of `radius` just fits a `fovDeg` view: a
   * little nearer, since what fills a box seldom reaches the sphere around it. */
  frame(centre, radius, fovDeg) {
    this.target = centre.slice();
    this.distance = (0.9 * radius) / Math.sin((fovDeg * Math.PI) / 360);
    this.onChange();
  }

  /** Where the eye is, [x, y, z]. */
  eye() {
    const [x, y, z] = this.target;
    const flat = this.distance * Math.cos(this.elevation);
    return [
      x + flat * Math.cos(this.azimuth),
      y + flat * Math.sin(this.azimuth),
      z + this.distance * Math.sin(this.elevation),
    ];
  }

  down(e) {
    this.element.setPointerCapture(e.pointerId);
    this.pointers.set(e.pointerId, [e.clientX, e.clientY]);
    this.pinch = this.spread();
    this.panning = e.button === 2 || e.shiftKey;
  }

  move(e) {
    const last = this.pointers.get(e.pointerId);
    if (!last) return;
    const dx = e.clientX - last[0];
    const dy = e.clientY - last[1];
    this.pointers.set(e.pointerId, [e.clientX, e.clientY]);
    if (this.pointers.size > 1) {
      const spread = this.spread();
      if (this.pinch > 0 && spread > 0) this.zoom(this.pinch / spread);
      this.pinch = spread;
    } else if (this.panning) {
      this.pan(dx, dy);
    } else {
      this.azimuth -= dx * TURN_PER_PIXEL;
      this.elevation = Math.max(-LIMIT, Math.min(LIMIT, this.elevation + dy * TURN_PER_PIXEL));
      this.onChange();
    }
  }

  up(e) {
    this.pointers.delete(e.pointerId);
    this.pinch = this.spread();
  }

  wheel(e) {
    e.preventDefault(); // the page does not scroll while the pointer zooms the view
    this.zoom(Math.exp(e.deltaY * ZOOM_PER_WHEEL));
  }

  zoom(factor) {
    this.distance = Math.max(1e-3, this.distance * factor);
    this.onChange();
  }

  /** Move the target with the pointer, across the screen's plane. */
  pan(dx, dy) {
    const per = this.distance / Math.max(this.element.clientHeight, 1);
    const sa = Math.sin(this.azimuth);
    const ca = Math.cos(this.azimuth);
    const se = Math.sin(this.elevation);
    const right = [-sa, ca, 0];
    const up = [-se * ca, -se * sa, Math.cos(this.elevation)];
    for (let k = 0; k < 3; k++) this.target[k] += per * (-dx * right[k] + dy * up[k]);
    this.onChange();
  }

  /** The distance between the first two pointers down (0 with fewer). */
  spread() {
    const [a, b] = [...this.pointers.values()];
    return a && b ? Math.hypot(a[0] - b[0], a[1] - b[1]) : 0;
  }
}
