// The front of a synthesis (`front: true`): for each joint count, the best result that beats
// every simpler one, as a small table of joints against chamfer; a row's click chooses it.

/** Fill `table` (its tbody) with one row per result, in the answer's order (joints
 * ascending); `onChoose(i)` on a row's click or Enter. */
export function renderFront(table, results, onChoose) {
  const body = table.tBodies[0];
  body.replaceChildren();
  const timed = results.some((r) => typeof r.timed_error === "number");
  table.classList.toggle("timed", timed);
  results.forEach((result, i) => {
    const row = document.createElement("tr");
    row.dataset.testid = "front-row";
    row.dataset.joints = String(result.n_joints);
    row.dataset.chamfer = String(result.chamfer);
    const error = result.timed_error;
    if (typeof error === "number") row.dataset.timedError = String(error);
    row.tabIndex = 0;
    row.setAttribute("aria-selected", "false");
    const cells = [String(result.n_joints), result.chamfer.toPrecision(4)];
    if (timed) cells.push(typeof error === "number" ? error.toPrecision(4) : "–");
    for (const text of cells) {
      const cell = document.createElement("td");
      cell.textContent = text;
      row.append(cell);
    }
    row.addEventListener("click", () => onChoose(i));
    row.addEventListener("keydown", (e) => {
      if (e.key === "Enter" || e.key === " ") {
        e.preventDefault();
        onChoose(i);
      }
    });
    body.append(row);
  });
  table.hidden = results.length === 0;
}

/** Mark row `i` as the one shown (-1: none). */
export function markFront(table, i) {
  for (const [j, row] of [...table.tBodies[0].rows].entries()) {
    row.setAttribute("aria-selected", String(i === j));
  }
}
