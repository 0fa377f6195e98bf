// What the browser tests read, in one place: window.__miss is this object. Pages and
// panels keep plain snapshots in it: ready, mode, triangles, background and sides
// ('front' | 'double' a part: the faces it draws) (the viewer), drawn ('preview' |
// 'full': what the owner's page drew while the job ran), cameraLps (the page), room
// (the consultation), structures, replay.
export const status = { ready: false, mode: null, triangles: 0 };
window.__miss = status;
