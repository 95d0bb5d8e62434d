// How the page words the facts of a finished job: plain functions of the job's JSON, no DOM, so that they run
// (and are tested) without a browser as well as in the page.

// "faces: achieved / target": the faces a job made, and where a face count was asked for (target_faces), that
// target and whether the count holds (the server's target_met: within +-tolerance of the target; the tolerance,
// a share such as 0.2, is the one the server states in /web/config.json).
export function faceCount(result, tolerance) {
  const q = result?.quality || {};
  const achieved = result?.faces ?? q.faces;
  if (achieved == null) return null;
  if (q.target_faces == null) return String(achieved);
  const band = tolerance == null ? 'the tolerance' : `±${Math.round(tolerance * 100)} %`;
  const held = q.target_met ? `within ${band}` : `outside ${band}`;
  return `${achieved} / ${q.target_faces} (${held})`;
}
