// Edge collapse with the surviving vertex placed by the quadric, within a proven bound:
// the kernel of miss.decimate.placed, in native code (built at install by setup.py, called
// through ctypes, which lets go of the GIL for the call).
//
// A collapse of the edge u-w removes u and moves w to a point p: the patch of triangles
// round u and w (their two fans, the two triangles on the edge once) is replaced by the
// fan from p over the patch's outer loop. p is where the sum of u's and w's quadrics
// (Garland and Heckbert's plane quadrics of the input triangles, area-weighted) is least;
// where that is ill-posed (a flat or a straight stretch) the least along the edge; then w
// and u as they are (a half-edge collapse), in that order, the first that holds.
//
// The bound is vertex removal's overlay bound (miss.decimate._fan.overlay_gap) carried
// over to two fans: both the old patch and the new fan are seen along the old patch's
// mean normal N. Where every old and every new triangle faces along N and each surface
// covers the loop's outline once, both are graphs of a height over that outline, so a
// point of either lies straight above (or below) a point of the other, within the
// difference of their heights there. That difference is linear over each overlap of an old
// and a new triangle, so it is largest at a corner of one: u, w (the new fan's height
// beneath them), p (the old patch's height beneath it), or a crossing of an old inner edge
// with a new one; the loop's vertices and edges lie on both (0).
//
// What each triangle has spent is an error box (after Cohen, Manocha and Olano's successive
// mappings, 1997): every input point that the collapses so far map to a point z of the
// triangle (and every point z mapped from one) is z + a vector in the box, axis-aligned in
// patient space, holding 0. A collapse maps a point of an old triangle t straight along N
// to the new triangle i above or below it, so that vector gains the signed height
// difference there times N: each new triangle's box is the hull, over the old triangles it
// overlaps, of t's box grown by N times the least to the most difference over their overlap
// (with 0). A collapse goes only if each new box's farthest corner is within the bound: the
// output is within the bound of the input everywhere, both ways, however the collapses
// chain. Signs are what the box adds to a distance alone: where one collapse lifts the
// surface and the next lowers it, their differences cancel (CThead bone at 0.002: 88 316
// triangles against 99 582 with one distance per triangle).
//
// Refused: a vertex on a boundary or pinched (its triangles are not one closed fan), a
// locked vertex that would move (a locked vertex may stay and take its neighbour in), a
// collapse that changes the topology (the two loops share a vertex besides the edge's two
// neighbours, or the patch's loop would close a tetrahedron), a new triangle degenerate or
// not facing along N, a vertex with more than `cap` triangles, or a cost past the bound.
//
// Order: cheapest first by quadric error, from a heap of vertices keyed by their cheapest
// edge (kept exact: a vertex remembers the neighbour across it, and is weighed again when
// that edge changes); each vertex tries its four cheapest edges (on the MR head at 0.002,
// before keys were exact: 1 189 798 triangles; two kept 1 227 072). The run is staged
// (fractions of the bound, rising), as the numba half-edge collapse's.
//
// Work not done (the same models within 0.2 %, the kernel 31 % faster on the MR head and 37 %
// on CThead bone): what the spots of one edge share (N, the frame, the old patch's areas) is
// worked out once per edge, and an edge whose old patch has no height over its outline
// weighs no spot; an overlay stops as soon as a sure overlap's grown box passes the bound,
// not only a difference alone.

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <exception>
#include <limits>
#include <thread>
#include <vector>

namespace {

const double kInf = std::numeric_limits<double>::infinity();
const int kCandidates = 4;   // the cheapest edges of a vertex that are tried
const double kDegenerate = 1e-6;  // 2 x area below this x the squared longest edge

struct V3 {
    double x, y, z;
};
inline V3 sub(V3 a, V3 b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
inline V3 cross(V3 a, V3 b) {
    return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}
inline double dot(V3 a, V3 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
inline double cross2(double ax, double ay, double bx, double by) { return ax * by - ay * bx; }

// What every worker shares: the mesh being collapsed and its tables.
struct Shared {
    std::vector<int32_t> vf;  // (N, row) vertex -> faces
    std::vector<int32_t> vdeg;
    std::vector<double> q;  // (N, 10) quadrics
    std::vector<float> terr;  // (M, 6) each triangle's error box, least corner then most
    std::vector<double> need;  // (N,) least bound a vertex's collapses need (0: unknown)
    std::vector<int32_t> pos;  // (N,) each vertex's place in its worker's heap (-1: none)
    std::vector<int32_t> via;  // (N,) the neighbour across a vertex's cheapest edge
};

// One worker: a stage over the vertices it owns (a slab's, or all), with its own heap and
// scratch; the arrays it points to are shared.
struct Run {
    double* pts;  // (N, 3), moved in place
    int32_t* faces;  // (M, 3), edited in place
    uint8_t* alive;  // (M,)
    const uint8_t* locked;  // (N,)
    int64_t n_pts;
    int cap;  // most triangles a new vertex may carry
    int row;  // the table's row length (>= cap, >= the input's largest valence)
    int32_t* vf;
    int32_t* vdeg;
    double* q;
    float* terr;
    double* need;
    int32_t* pos;
    int32_t* via;
    // the worker's vertices: owner[v] == me (all, where owner is null)
    const int32_t* owner = nullptr;
    int32_t me = 0;
    std::vector<double> key;  // heap
    std::vector<int32_t> item;
    int64_t size = 0;
    // what the run did: pops tried, pops put back at their cost, overlays weighed, and
    // collapses to the quadric's point, to w, to u
    int64_t n_tries = 0, n_rekeyed = 0, n_overlays = 0, n_spot[3] = {0, 0, 0};

    // scratch (fans of up to `row` triangles; patches of up to 2 x row)
    std::vector<int32_t> fan_u, loop_u, fan_w, loop_w, as, bs, used, loop, patch;
    std::vector<int32_t> old_tri;  // local corners of the old patch's triangles
    // the old patch's inner edges (an end at u or w), each once: (a, b, t, s), a < b local
    // corners, t and s the old triangles beside it
    std::vector<int32_t> inner;
    int n_inner = 0;
    std::vector<double> xs, ys, hs, sq, old_area, ang, unw, ins, old_box, trial, best, box;
    // the candidate's frame (see frame)
    V3 fo, fn, fe, ff;
    double outline = 0.0, old_sum = 0.0;
    std::vector<double> ccost;
    std::vector<V3> cspot;  // where each of u's edges would put the vertex
    std::vector<int32_t> corder;
    // (old x new) the least and the most height difference over their overlap
    std::vector<double> d_lo, d_hi;

    V3 P(int32_t v) const { return {pts[3 * v], pts[3 * v + 1], pts[3 * v + 2]}; }
    bool mine(int32_t v) const { return owner == nullptr || owner[v] == me; }

    void attach(double* p, int32_t* f, uint8_t* a, const uint8_t* l, int64_t n, int c, int r,
                Shared& s) {
        pts = p, faces = f, alive = a, locked = l, n_pts = n, cap = c, row = r;
        vf = s.vf.data(), vdeg = s.vdeg.data(), q = s.q.data(), terr = s.terr.data();
        need = s.need.data(), pos = s.pos.data(), via = s.via.data();
        int a1 = row + 1, a2 = 2 * row + 4;
        for (auto* v : {&fan_u, &loop_u, &fan_w, &loop_w, &as, &bs, &used, &corder})
            v->assign(a1, 0);
        loop.assign(a2, 0);
        patch.assign(a2, 0);
        old_tri.assign(3 * a2, 0);
        inner.assign(4 * 3 * a2, 0);
        for (auto* v : {&xs, &ys, &hs, &sq, &old_area, &ang, &unw, &ins}) v->assign(a2 + 3, 0.0);
        for (auto* v : {&old_box, &trial, &best, &box}) v->assign(6 * (a2 + 3), 0.0);
        ccost.assign(a1, 0.0);
        cspot.assign(a1, V3{0.0, 0.0, 0.0});
        d_lo.assign(size_t(a2) * size_t(a1), 0.0);
        d_hi.assign(size_t(a2) * size_t(a1), 0.0);
    }

    // ------------------------------------------------------------------ quadrics
    void plane_quadrics(int64_t n_faces) {
        for (int64_t f = 0; f < n_faces; ++f) {
            int32_t a = faces[3 * f], b = faces[3 * f + 1], c = faces[3 * f + 2];
            V3 n = cross(sub(P(b), P(a)), sub(P(c), P(a)));
            double len = std::sqrt(dot(n, n));
            if (len == 0.0) continue;
            double w = 0.5 * len;
            n = {n.x / len, n.y / len, n.z / len};
            double d = -dot(n, P(a));
            double r[10] = {n.x * n.x, n.x * n.y, n.x * n.z, n.x * d, n.y * n.y,
                            n.y * n.z, n.y * d,   n.z * n.z, n.z * d, d * d};
            for (int32_t u : {a, b, c})
                for (int k = 0; k < 10; ++k) q[10 * u + k] += w * r[k];
        }
    }

    static double q_at(const double* Q, V3 p) {
        return Q[0] * p.x * p.x + 2 * Q[1] * p.x * p.y + 2 * Q[2] * p.x * p.z + 2 * Q[3] * p.x +
               Q[4] * p.y * p.y + 2 * Q[5] * p.y * p.z + 2 * Q[6] * p.y + Q[7] * p.z * p.z +
               2 * Q[8] * p.z + Q[9];
    }

    // Where the collapse of u-w puts the vertex, and its quadric cost there.
    double place(int32_t u, int32_t w, V3& p) const {
        bool lu = locked[u], lw = locked[w];
        double Q[10];
        for (int k = 0; k < 10; ++k) Q[k] = q[10 * u + k] + q[10 * w + k];
        if (lu && lw) {
            p = P(w);
            return kInf;
        }
        if (lu || lw) {
            p = P(lu ? u : w);
            return std::max(0.0, q_at(Q, p));
        }
        V3 a = P(u), b = P(w);
        V3 e = sub(b, a);
        double e2 = dot(e, e);
        // the least of Q: A p = -b, by Cramer's rule where A is well-conditioned
        double a00 = Q[0], a01 = Q[1], a02 = Q[2], a11 = Q[4], a12 = Q[5], a22 = Q[7];
        double c0 = a11 * a22 - a12 * a12, c1 = a02 * a12 - a01 * a22, c2 = a01 * a12 - a02 * a11;
        double det = a00 * c0 + a01 * c1 + a02 * c2;
        double norm = std::sqrt(a00 * a00 + a11 * a11 + a22 * a22 +
                                2 * (a01 * a01 + a02 * a02 + a12 * a12));
        if (norm > 0.0 && std::fabs(det) > 1e-3 * norm * norm * norm) {
            double b0 = -Q[3], b1 = -Q[6], b2 = -Q[8];
            double d1 = a02 * a12 - a01 * a22;  // adjugate, symmetric
            double d2 = a01 * a12 - a02 * a11;
            double e11 = a00 * a22 - a02 * a02, e12 = a01 * a02 - a00 * a12;
            double e22 = a00 * a11 - a01 * a01;
            V3 s = {(c0 * b0 + d1 * b1 + d2 * b2) / det, (d1 * b0 + e11 * b1 + e12 * b2) / det,
                    (d2 * b0 + e12 * b1 + e22 * b2) / det};
            V3 mid = {0.5 * (a.x + b.x), 0.5 * (a.y + b.y), 0.5 * (a.z + b.z)};
            V3 off = sub(s, mid);
            if (std::isfinite(s.x + s.y + s.z) && dot(off, off) <= e2) {
                p = s;
                return std::max(0.0, q_at(Q, p));
            }
        }
        // along the edge: Q(a + t e) = alpha t^2 + 2 beta t + gamma, least in [0, 1]
        double t = 0.5;
        double Ae[3] = {a00 * e.x + a01 * e.y + a02 * e.z, a01 * e.x + a11 * e.y + a12 * e.z,
                        a02 * e.x + a12 * e.y + a22 * e.z};
        double alpha = Ae[0] * e.x + Ae[1] * e.y + Ae[2] * e.z;
        double beta = Ae[0] * a.x + Ae[1] * a.y + Ae[2] * a.z + Q[3] * e.x + Q[6] * e.y +
                      Q[8] * e.z;
        if (alpha > 0.0) t = std::min(1.0, std::max(0.0, -beta / alpha));
        p = {a.x + t * e.x, a.y + t * e.y, a.z + t * e.z};
        return std::max(0.0, q_at(Q, p));
    }

    // u's neighbours (the corner after u in each of its triangles), one per triangle
    int32_t next_corner(int32_t f, int32_t u) const {
        const int32_t* c = faces + 3 * f;
        return c[0] == u ? c[1] : (c[1] == u ? c[2] : c[0]);
    }

    // u's cheapest edge's cost (via[u]: the neighbour across it)
    double vertex_cost(int32_t u) {
        double best = kInf;
        V3 p;
        for (int k = 0; k < vdeg[u]; ++k) {
            int32_t x = next_corner(vf[size_t(u) * row + k], u);
            double c = place(u, x, p);
            if (c < best) best = c, via[u] = x;
        }
        return best;
    }

    // ------------------------------------------------------------------ fans
    // u's triangles chained round it (fan) and the loop of its neighbours; the loop's
    // triangle k is (u, loop[k], loop[k+1]). False where they are not one closed fan.
    bool order_fan(int32_t u, int32_t* fan, int32_t* lp) {
        int n = vdeg[u];
        if (n < 3) return false;
        const int32_t* r = &vf[size_t(u) * row];
        for (int k = 0; k < n; ++k) {
            const int32_t* c = faces + 3 * r[k];
            int i = c[0] == u ? 0 : (c[1] == u ? 1 : 2);
            as[k] = c[(i + 1) % 3];
            bs[k] = c[(i + 2) % 3];
            used[k] = 0;
        }
        int cur = 0;
        used[0] = 1;
        for (int step = 0; step < n; ++step) {
            fan[step] = r[cur];
            lp[step] = as[cur];
            int32_t want = bs[cur];
            if (step == n - 1) return want == as[0];
            int nk = -1;
            for (int k = 0; k < n; ++k)
                if (!used[k] && as[k] == want) {
                    nk = k;
                    break;
                }
            if (nk < 0) return false;
            used[nk] = 1;
            cur = nk;
        }
        return false;
    }

    bool face_exists(int32_t a, int32_t b, int32_t c) const {
        for (int k = 0; k < vdeg[a]; ++k) {
            const int32_t* f = faces + 3 * vf[size_t(a) * row + k];
            int hits = 0;
            for (int m = 0; m < 3; ++m) hits += (f[m] == b || f[m] == c);
            if (hits == 2) return true;
        }
        return false;
    }

    // ------------------------------------------------------------------ the bound
    // x as a float at or below it, at or above it (a box kept in floats still holds)
    static float below(double x) {
        float f = float(x);
        return double(f) > x ? std::nextafter(f, -std::numeric_limits<float>::infinity()) : f;
    }
    static float above(double x) {
        float f = float(x);
        return double(f) < x ? std::nextafter(f, std::numeric_limits<float>::infinity()) : f;
    }
    // the farthest corner of a box (least corner, most corner) from 0
    template <typename T>
    static double reach(const T* b) {
        double s = 0.0;
        for (int k = 0; k < 3; ++k)
            s += std::max(double(b[k]) * b[k], double(b[3 + k]) * b[3 + k]);
        return std::sqrt(s);
    }
    // Local points: 0 = u, 1 = w (where they are), 2 = p, 3 + i = loop[i]. The old patch's
    // triangles are old_tri (n_old x 3, local corners), each with its error box in old_box;
    // the new fan's triangle i is (2, 3 + i, 3 + i + 1).
    //
    // The candidate's frame, what does not depend on where the vertex goes: N, the old
    // patch's mean normal, e and f across it, every local point but p seen from w along N
    // (xs, ys across, hs along), the old triangles' areas and the outline's. False where the
    // old patch has no height over the outline (N is 0 or an old triangle is folded back):
    // then no spot holds.
    bool frame(int32_t u, int32_t w, int n_loop, int n_old) {
        V3 o = P(w);
        auto local = [&](int i) -> V3 {
            return i == 0 ? P(u) : (i == 1 ? P(w) : P(loop[i - 3]));
        };
        V3 N = {0, 0, 0};
        for (int t = 0; t < n_old; ++t) {
            V3 a = local(old_tri[3 * t]), b = local(old_tri[3 * t + 1]),
               c = local(old_tri[3 * t + 2]);
            V3 n = cross(sub(b, a), sub(c, a));
            N = {N.x + n.x, N.y + n.y, N.z + n.z};
        }
        double len = std::sqrt(dot(N, N));
        if (!(len > 0.0)) return false;
        N = {N.x / len, N.y / len, N.z / len};
        V3 e;
        if (std::fabs(N.x) <= std::fabs(N.y) && std::fabs(N.x) <= std::fabs(N.z))
            e = {0.0, N.z, -N.y};
        else if (std::fabs(N.y) <= std::fabs(N.z))
            e = {-N.z, 0.0, N.x};
        else
            e = {N.y, -N.x, 0.0};
        double el = std::sqrt(dot(e, e));
        e = {e.x / el, e.y / el, e.z / el};
        fo = o, fn = N, fe = e, ff = cross(N, e);
        for (int i = 0; i < 3 + n_loop; ++i) {
            if (i == 2) continue;
            V3 d = sub(local(i), o);
            xs[i] = dot(fe, d);
            ys[i] = dot(ff, d);
            hs[i] = dot(fn, d);
            sq[i] = xs[i] * xs[i] + ys[i] * ys[i];
        }
        outline = 0.0;
        for (int i = 0; i < n_loop; ++i) {
            int a = 3 + i, b = 3 + (i + 1) % n_loop;
            outline += cross2(xs[a], ys[a], xs[b], ys[b]);
        }
        old_sum = 0.0;
        for (int t = 0; t < n_old; ++t) {
            double s = area(old_tri[3 * t], old_tri[3 * t + 1], old_tri[3 * t + 2]);
            if (s <= 0.0) return false;  // an old triangle folded back: no height over it
            old_area[t] = s;
            old_sum += s;
        }
        return true;
    }

    double area(int a, int b, int c) const {
        return cross2(xs[b] - xs[a], ys[b] - ys[a], xs[c] - xs[a], ys[c] - ys[a]);
    }

    // In the frame: fills spent[6 i, 6 i + 6) with new triangle i's error box (see the
    // header) where the vertex goes to p. Returns the farthest any new box reaches, inf
    // where the bound does not apply, or, as soon as a difference alone or a sure overlap's
    // grown box (below) passes `limit`, how far that reaches (a new box reaches at least as
    // far: it holds 0, and each such grown box).
    double overlay(V3 p, int n_loop, int n_old, double limit, double* spent) {
        V3 N = fn;
        {
            V3 d = sub(p, fo);
            xs[2] = dot(fe, d);
            ys[2] = dot(ff, d);
            hs[2] = dot(fn, d);
            sq[2] = xs[2] * xs[2] + ys[2] * ys[2];
        }
        int n_pts = 3 + n_loop;
        double scale = 0.0;
        for (int i = 0; i < n_pts; ++i) scale += sq[i];
        double tol = 1e-9 * scale;
        double new_sum = 0.0;
        for (int i = 0; i < n_loop; ++i) {
            double s = area(2, 3 + i, 3 + (i + 1) % n_loop);
            if (s <= 0.0) return kInf;  // a new triangle folded back
            new_sum += s;
        }
        if (!(std::fabs(old_sum - outline) <= tol) || !(std::fabs(new_sum - outline) <= tol))
            return kInf;  // one of them winds round more than once (or a figure is not one)
        // The least and the most height difference (old minus new) over each overlap of an
        // old triangle t and a new one i, d_lo and d_hi[t * n_loop + i], with 0. It is
        // linear there, so least and most at corners of the overlap: p (a corner of every
        // new triangle) where it lies in t; u or w where t has it as a corner and it lies
        // in i; a crossing of an inner edge of t (an end at u or w) with an edge of i from
        // p; or a loop vertex (0). (t's other edges and i's third edge lie on the loop's
        // outline.) A point on an edge counts for the triangles on both sides. Each overlap
        // counts on its own: an old triangle's box grows only by the differences over it.
        const double kSlack = 1e-9;
        double top = 0.0;  // the largest difference so far
        double* lo_d = d_lo.data();
        double* hi_d = d_hi.data();
        std::fill(lo_d, lo_d + size_t(n_old) * size_t(n_loop), 0.0);
        std::fill(hi_d, hi_d + size_t(n_old) * size_t(n_loop), 0.0);
        auto add = [&](int t, int i, double d) {
            size_t k = size_t(t) * n_loop + i;
            lo_d[k] = std::min(lo_d[k], d);
            hi_d[k] = std::max(hi_d[k], d);
            top = std::max(top, std::fabs(d));
        };
        // A sure overlap of old triangle t with a new one (p inside t, or u or w inside the new
        // one, or a crossing inside both edges) grows that new one's box by at least t's box
        // grown by d N: reach2 keeps the farthest such a box reaches (squared), to stop early.
        const double n3[3] = {N.x, N.y, N.z};
        double reach2 = 0.0;
        auto grow = [&](int t, double d) {
            const double* ob = &old_box[6 * t];
            double r2 = 0.0;
            for (int m = 0; m < 3; ++m) {
                double a = d * n3[m];
                double lo = ob[m] + std::min(0.0, a), hi = ob[3 + m] + std::max(0.0, a);
                r2 += std::max(lo * lo, hi * hi);
            }
            reach2 = std::max(reach2, r2);
        };
        // (a box reaches at least as far as any difference and any sure grown box)
        auto past = [&]() { return std::max(top, std::sqrt(reach2)); };
        {
            int hold = -1;
            double best = -kInf, height = 0.0;
            for (int t = 0; t < n_old; ++t) {
                int a = old_tri[3 * t], b = old_tri[3 * t + 1], c = old_tri[3 * t + 2];
                double s = old_area[t];
                double la = area(2, b, c) / s, lb = area(a, 2, c) / s, lc = 1.0 - la - lb;
                double inside = std::min(la, std::min(lb, lc));
                ins[t] = inside;
                if (inside > best) {
                    best = inside;
                    height = la * hs[a] + lb * hs[b] + lc * hs[c];
                    hold = t;
                }
            }
            double dp = height - hs[2];
            for (int t = 0; t < n_old; ++t)
                if (t == hold || ins[t] >= -kSlack) {
                    for (int i = 0; i < n_loop; ++i) add(t, i, dp);
                    if (ins[t] > kSlack) grow(t, dp);
                }
        }
        if (past() > limit) return past();
        for (int v = 0; v < 2; ++v) {
            int hold = -1;
            double best = -kInf, height = 0.0;
            for (int i = 0; i < n_loop; ++i) {
                int b = 3 + i, c = 3 + (i + 1) % n_loop;
                double s = area(2, b, c);
                double la = area(v, b, c) / s, lb = area(2, v, c) / s, lc = 1.0 - la - lb;
                double inside = std::min(la, std::min(lb, lc));
                if (inside > best) {
                    best = inside;
                    height = la * hs[2] + lb * hs[b] + lc * hs[c];
                    hold = i;
                }
            }
            double d = hs[v] - height;
            bool sure = false;
            for (int i = 0; i < n_loop; ++i) {
                int b = 3 + i, c = 3 + (i + 1) % n_loop;
                double s = area(2, b, c);
                double inside = std::min(area(v, b, c), std::min(area(2, v, c), area(2, b, v))) / s;
                if (i != hold && inside < -kSlack) continue;
                sure = sure || inside > kSlack;
                for (int t = 0; t < n_old; ++t)
                    if (old_tri[3 * t] == v || old_tri[3 * t + 1] == v || old_tri[3 * t + 2] == v)
                        add(t, i, d);
            }
            if (sure)
                for (int t = 0; t < n_old; ++t)
                    if (old_tri[3 * t] == v || old_tri[3 * t + 1] == v || old_tri[3 * t + 2] == v)
                        grow(t, d);
            if (past() > limit) return past();
        }
        // the old inner edges against the new edges from p (each crossing is in the two
        // old triangles beside the one and the two new ones beside the other)
        for (int e = 0; e < n_inner; ++e) {
            const int32_t* g = &inner[4 * e];
            int a = g[0], b = g[1], t = g[2], t2 = g[3];
            double sx = xs[b] - xs[a], sy = ys[b] - ys[a];
            double wx = xs[2] - xs[a], wy = ys[2] - ys[a];
            for (int i = 0; i < n_loop; ++i) {
                int c = 3 + i;
                if (b == c) continue;  // they meet at the loop vertex (0 there)
                double tx = xs[c] - xs[2], ty = ys[c] - ys[2];
                double d = cross2(sx, sy, tx, ty);
                if (d == 0.0) continue;  // parallel: their ends are measured already
                double s = cross2(wx, wy, tx, ty) / d;  // along the old edge
                double r = cross2(wx, wy, sx, sy) / d;  // along the new one
                if (s >= 0.0 && s <= 1.0 && r >= 0.0 && r <= 1.0) {
                    double ho = hs[a] + s * (hs[b] - hs[a]);
                    double hn = hs[2] + r * (hs[c] - hs[2]);
                    double diff = ho - hn;
                    int h = (i + n_loop - 1) % n_loop;
                    add(t, i, diff);
                    add(t, h, diff);
                    add(t2, i, diff);
                    add(t2, h, diff);
                    if (s > 0.0 && s < 1.0 && r > 0.0 && r < 1.0) grow(t, diff), grow(t2, diff);
                }
            }
            if (past() > limit) return past();
        }
        // Each new triangle's box: the hull, over the old triangles it overlaps, of the old
        // box grown by N times their overlap's differences. The new fan is star-shaped
        // from p, so new triangle i is the outline within the angle from loop[i] to
        // loop[i + 1] seen from p, and an old triangle overlaps it where their angles
        // overlap; touching is not overlapping (a point where they touch is a limit of
        // points inside the ones that do overlap, within their error).
        // Angles are pseudo-angles (diamond angles: a turn is 4, monotone in the angle,
        // opposite directions 2 apart), which is all this needs.
        const double kTurn = 4.0, kTouch = 1e-12;
        for (int i = 0; i < n_pts; ++i) {
            double dx = xs[i] - xs[2], dy = ys[i] - ys[2];
            if (dx == 0.0 && dy == 0.0)
                ang[i] = kInf;
            else if (dy >= 0.0)
                ang[i] = dx >= 0.0 ? dy / (dx + dy) : 1.0 - dx / (dy - dx);
            else
                ang[i] = dx < 0.0 ? 2.0 - dy / (-dx - dy) : 3.0 + dx / (dx - dy);
        }
        // the loop's angles unwrapped: rising from the first by each sector's width
        unw[0] = ang[3];
        for (int i = 1; i <= n_loop; ++i) {
            double width = (i < n_loop ? ang[3 + i] : ang[3]) - ang[3 + i - 1];
            if (width < 0.0) width += kTurn;
            unw[i] = unw[i - 1] + width;
        }
        for (int i = 0; i < 6 * n_loop; ++i) box[i] = i % 6 < 3 ? kInf : -kInf;
        auto merge = [&](int t, int i) {
            size_t k = size_t(t) * n_loop + i;
            const double* ob = &old_box[6 * t];
            double* b = &box[6 * i];
            for (int m = 0; m < 3; ++m) {
                double a1 = lo_d[k] * n3[m], a2 = hi_d[k] * n3[m];
                b[m] = std::min(b[m], ob[m] + std::min(a1, a2));
                b[3 + m] = std::max(b[3 + m], ob[3 + m] + std::max(a1, a2));
            }
        };
        for (int t = 0; t < n_old; ++t) {
            int a = old_tri[3 * t], b = old_tri[3 * t + 1], c = old_tri[3 * t + 2];
            double sa = old_area[t];
            double inside = std::min(area(2, b, c), std::min(area(a, 2, c), area(a, b, 2)));
            if (inside >= kSlack * sa) {  // p in it: it overlaps them all
                for (int i = 0; i < n_loop; ++i) merge(t, i);
                continue;
            }
            // p outside: it spans less than a half turn, [lo, hi], the complement of the
            // largest gap between its corners' angles
            double th[3];
            int m = 0;
            for (int k : {a, b, c})
                if (ang[k] != kInf) th[m++] = ang[k];
            std::sort(th, th + m);
            double gap = -1.0, lo = 0.0;
            for (int k = 0; k < m; ++k) {
                double next = k + 1 < m ? th[k + 1] : th[0] + kTurn;
                if (next - th[k] > gap) {
                    gap = next - th[k];
                    lo = k + 1 < m ? th[k + 1] : th[0];
                }
            }
            double hi = lo + (kTurn - gap);
            while (lo < unw[0]) lo += kTurn, hi += kTurn;
            while (lo >= unw[0] + kTurn) lo -= kTurn, hi -= kTurn;
            for (int i = 0; i < n_loop; ++i) {
                // the sector [unw[i], unw[i + 1]] against [lo, hi] and, past a whole turn,
                // [lo - turn, hi - turn]
                if ((lo < unw[i + 1] - kTouch && hi > unw[i] + kTouch) ||
                    (hi - kTurn > unw[i] + kTouch))
                    merge(t, i);
            }
        }
        top = 0.0;
        for (int i = 0; i < n_loop; ++i) {
            for (int m = 0; m < 6; ++m) spent[6 * i + m] = box[6 * i + m];
            top = std::max(top, reach(&box[6 * i]));
        }
        return top;
    }

    // no new triangle degenerate (their facing is the overlay's to check)
    bool upright(V3 p, int n_loop) const {
        for (int i = 0; i < n_loop; ++i) {
            V3 b = P(loop[i]), c = P(loop[(i + 1) % n_loop]);
            V3 x = sub(b, p), y = sub(c, p), z = sub(c, b);
            V3 n = cross(x, y);
            double longest = std::max(dot(x, x), std::max(dot(y, y), dot(z, z)));
            if (std::sqrt(dot(n, n)) <= kDegenerate * longest) return false;
        }
        return true;
    }

    // ------------------------------------------------------------------ one collapse
    // u into a neighbour (its cheapest kCandidates edges), if one is valid and within the
    // bound. Returns the triangles freed (2), or -1 with `needed` the least bound under
    // which one of those weighed could go while the fans stay as they are.
    int try_collapse(int32_t u, double bound, double key_u, double& needed) {
        needed = kInf;
        n_tries++;
        int n_u = vdeg[u];
        if (!order_fan(u, fan_u.data(), loop_u.data())) return -1;
        double carried_u = kInf;  // the least far any of u's triangles' boxes reach
        for (int k = 0; k < n_u; ++k) carried_u = std::min(carried_u, reach(&terr[6 * fan_u[k]]));
        if (carried_u >= bound) {
            needed = carried_u;
            return -1;
        }
        // the candidates, cheapest first (insertion: a dozen at most)
        int m = 0;
        for (int k = 0; k < n_u; ++k) {
            double c = place(u, loop_u[k], cspot[k]);
            int i = m;
            while (i > 0 && ccost[i - 1] > c) {
                ccost[i] = ccost[i - 1];
                corder[i] = corder[i - 1];
                --i;
            }
            ccost[i] = c;
            corder[i] = k;
            ++m;
        }
        if (m > 0 && ccost[0] > key_u && ccost[0] < kInf) {
            needed = ccost[0];  // a key below its cost (kept exact: not seen): back, at it
            via[u] = loop_u[corder[0]];
            return -2;
        }
        for (int ci = 0; ci < std::min(m, kCandidates); ++ci) {
            if (ccost[ci] == kInf) break;
            int j = corder[ci];
            int32_t w = loop_u[j];
            if (!mine(w)) continue;  // another worker's (or the guard's): its rows are theirs
            int n_w = vdeg[w];
            if (!order_fan(w, fan_w.data(), loop_w.data())) continue;
            // the patch's loop: u's loop after w, then w's loop after u's last, before u's
            // first (w's loop runs ..., u, a_last, ..., a_first, ...)
            int iu = -1;
            for (int k = 0; k < n_w; ++k)
                if (loop_w[k] == u) iu = k;
            if (iu < 0) continue;
            int n_loop = 0;
            for (int k = 1; k < n_u; ++k) loop[n_loop++] = loop_u[(j + k) % n_u];
            int32_t a_first = loop[0], a_last = loop[n_loop - 1];
            if (loop_w[(iu + 1) % n_w] != a_last || loop_w[(iu + n_w - 1) % n_w] != a_first)
                continue;  // not a manifold edge
            bool ok = true;
            for (int k = 2; k < n_w - 1 && ok; ++k) {
                int32_t b = loop_w[(iu + k) % n_w];
                for (int i = 0; i < n_u - 1; ++i)
                    if (loop[i] == b) ok = false;  // the loops share a vertex: a pinch
                loop[n_loop++] = b;
            }
            if (!ok || n_loop < 3 || n_loop > cap) continue;
            if (n_loop == 3 && face_exists(loop[0], loop[1], loop[2])) continue;
            // the old patch (u's fan, then w's without the two on the edge), local corners
            // (u's loop position q is loop[q - j - 1]; w's loop position iu + k is a_last
            // for k = 1, loop[n_u + k - 3] for k in 2 .. n_w - 2, a_first for k = n_w - 1)
            auto loc_u = [&](int q) { return q == j ? 1 : 3 + (q - j - 1 + n_u) % n_u; };
            auto loc_w = [&](int q) {
                int k = (q - iu + n_w) % n_w;
                return k == 0 ? 0 : (k == n_w - 1 ? 3 : 3 + n_u + k - 3);
            };
            int n_old = 0, n_patch = 0;
            for (int k = 0; k < n_u; ++k) {
                patch[n_patch++] = fan_u[k];
                std::copy(&terr[6 * fan_u[k]], &terr[6 * fan_u[k]] + 6, &old_box[6 * n_old]);
                old_tri[3 * n_old] = 0;
                old_tri[3 * n_old + 1] = loc_u(k);
                old_tri[3 * n_old + 2] = loc_u((k + 1) % n_u);
                ++n_old;
            }
            for (int k = 0; k < n_w; ++k) {
                int32_t a = loop_w[k], b = loop_w[(k + 1) % n_w];
                if (a == u || b == u) continue;
                patch[n_patch++] = fan_w[k];
                std::copy(&terr[6 * fan_w[k]], &terr[6 * fan_w[k]] + 6, &old_box[6 * n_old]);
                old_tri[3 * n_old] = 1;
                old_tri[3 * n_old + 1] = loc_w(k);
                old_tri[3 * n_old + 2] = loc_w((k + 1) % n_w);
                ++n_old;
            }
            if (!frame(u, w, n_loop, n_old)) continue;
            // the inner edges (an end at u or w; a < b) and the triangles beside each
            n_inner = 0;
            for (int t = 0; t < n_old; ++t)
                for (int k = 0; k < 3; ++k) {
                    int a = old_tri[3 * t + k], b = old_tri[3 * t + (k + 1) % 3];
                    if (a > b || a > 1) continue;
                    int twin = -1;
                    for (int t2 = 0; t2 < n_old && twin < 0; ++t2)
                        for (int k2 = 0; k2 < 3; ++k2)
                            if (old_tri[3 * t2 + k2] == b && old_tri[3 * t2 + (k2 + 1) % 3] == a)
                                twin = t2;
                    int32_t* g = &inner[4 * n_inner++];
                    g[0] = a, g[1] = b, g[2] = t, g[3] = twin < 0 ? t : twin;
                }
            // where w goes: the quadric's point, then w, then u as they are
            V3 spots[3];
            int n_spots = 0;
            spots[n_spots++] = cspot[j];
            spots[n_spots++] = P(w);
            if (!locked[w]) spots[n_spots++] = P(u);
            // the spot that spends least of the bound
            int chosen = -1;
            double least = kInf;
            for (int s = 0; s < n_spots; ++s) {
                V3 p = spots[s];
                if (s > 0 && p.x == spots[0].x && p.y == spots[0].y && p.z == spots[0].z)
                    continue;
                if (!upright(p, n_loop)) continue;
                n_overlays++;
                double spent = overlay(p, n_loop, n_old, std::min(least, bound), trial.data());
                if (spent < least) {
                    least = spent;
                    chosen = s;
                    std::copy(trial.begin(), trial.begin() + 6 * n_loop, best.begin());
                }
            }
            if (chosen >= 0 && least <= bound) {
                n_spot[chosen]++;
                commit(u, w, spots[chosen], n_loop, n_patch);
                return 2;
            }
            needed = std::min(needed, least);
        }
        return -1;
    }

    // Replaces the patch by the new fan (each new triangle carrying best[i]), reusing the
    // patch's face slots, and moves w to p.
    void commit(int32_t u, int32_t w, V3 p, int n_loop, int n_patch) {
        // loop vertices lose their patch triangles (those with a corner u or w) from
        // their rows
        for (int i = 0; i < n_loop; ++i) {
            int32_t x = loop[i];
            int32_t* r = &vf[size_t(x) * row];
            int keep = 0;
            for (int k = 0; k < vdeg[x]; ++k) {
                const int32_t* c = faces + 3 * r[k];
                bool in_patch = c[0] == u || c[1] == u || c[2] == u || c[0] == w ||
                                c[1] == w || c[2] == w;
                if (!in_patch) r[keep++] = r[k];
            }
            vdeg[x] = keep;
        }
        int32_t* rw = &vf[size_t(w) * row];
        for (int i = 0; i < n_loop; ++i) {
            int32_t f = patch[i];
            int32_t b = loop[i], c = loop[(i + 1) % n_loop];
            faces[3 * f] = w;
            faces[3 * f + 1] = b;
            faces[3 * f + 2] = c;
            for (int m = 0; m < 3; ++m) {
                terr[6 * f + m] = below(best[6 * i + m]);
                terr[6 * f + 3 + m] = above(best[6 * i + 3 + m]);
            }
            rw[i] = f;
            vf[size_t(b) * row + vdeg[b]++] = f;
            vf[size_t(c) * row + vdeg[c]++] = f;
        }
        vdeg[w] = n_loop;
        for (int t = n_loop; t < n_patch; ++t) alive[patch[t]] = 0;
        vdeg[u] = 0;
        pts[3 * w] = p.x;
        pts[3 * w + 1] = p.y;
        pts[3 * w + 2] = p.z;
        for (int k = 0; k < 10; ++k) q[10 * w + k] += q[10 * u + k];
    }

    // ------------------------------------------------------------------ the heap
    void swap_(int64_t i, int64_t j) {
        std::swap(key[i], key[j]);
        std::swap(item[i], item[j]);
        pos[item[i]] = int32_t(i);
        pos[item[j]] = int32_t(j);
    }
    void sift(int64_t i) {
        while (i > 0 && key[(i - 1) >> 1] > key[i]) {
            swap_(i, (i - 1) >> 1);
            i = (i - 1) >> 1;
        }
        for (;;) {
            int64_t c = 2 * i + 1;
            if (c >= size) return;
            if (c + 1 < size && key[c + 1] < key[c]) ++c;
            if (key[i] <= key[c]) return;
            swap_(i, c);
            i = c;
        }
    }
    void put(int32_t v, double cost) {
        int64_t i = pos[v];
        if (i < 0) {
            i = size++;
            item[i] = v;
            pos[v] = int32_t(i);
        }
        key[i] = cost;
        sift(i);
    }
    void remove(int32_t v) {
        int64_t i = pos[v];
        if (i < 0) return;
        --size;
        if (i != size) {
            swap_(i, size);
            sift(i);
        }
        pos[v] = -1;
    }
    int32_t pop() {
        int32_t v = item[0];
        --size;
        if (size > 0) {
            swap_(0, size);
            sift(0);
        }
        pos[v] = -1;
        return v;
    }

    // One stage at `bound` over the worker's vertices (visit: n_visit of them; null: all),
    // until `target` live triangles remain of `n_alive` or nothing more goes. Returns the
    // live triangles.
    int64_t stage(double bound, int64_t n_alive, int64_t target, const int32_t* visit,
                  int64_t n_visit) {
        key.assign(n_visit, 0.0);
        item.assign(n_visit, 0);
        size = 0;
        for (int64_t k = 0; k < n_visit; ++k) {
            int32_t u = visit ? visit[k] : int32_t(k);
            if (vdeg[u] > 0 && !locked[u] && pos[u] < 0 && need[u] <= bound) {
                double c = vertex_cost(u);
                if (c < kInf) put(u, c);
            }
        }
        // a locked vertex's edges are weighed from its free neighbours
        while (size > 0 && n_alive > target) {
            double key_u = key[0];
            int32_t u = pop();
            double needed;
            int freed = try_collapse(u, bound, key_u, needed);
            if (freed == -2) {
                ++n_rekeyed;
                put(u, needed);
                continue;
            }
            if (freed < 0) {
                need[u] = needed;
                continue;
            }
            n_alive -= freed;
            int32_t w = faces[3 * patch[0]];
            int n_loop = vdeg[w];
            // Keys: w's edges all changed; a loop vertex's only to w (and to u, gone). One
            // in the heap whose cheapest edge was to neither keeps the lower of its key and
            // its edge to w; the others are weighed again.
            for (int i = -1; i < n_loop; ++i) {
                int32_t x = i < 0 ? w : loop[i];
                need[x] = 0.0;
                if (locked[x] || !mine(x)) continue;
                double c;
                if (i >= 0 && pos[x] >= 0 && via[x] != u && via[x] != w) {
                    V3 p;
                    c = place(x, w, p);
                    if (c < key[pos[x]])
                        via[x] = w;
                    else
                        c = key[pos[x]];
                } else {
                    c = vertex_cost(x);
                }
                if (c < kInf)
                    put(x, c);
                else
                    remove(x);
            }
        }
        while (size > 0) pos[item[--size]] = -1;
        return n_alive;
    }
};


// Slabs side by side: the vertices of a slab (slab[v], set by position across the mesh) that
// no live triangle spanning two slabs touches (those are the guard's) have neighbours in
// their own slab only, and no two slabs share a neighbour; a collapse within a slab (both
// ends its own) joins two of its own fans, so that stays true. Each slab's collapses then
// read and write only its own vertices' rows, quadrics and positions and the triangles
// that touch them, whatever the other slabs do: the result is the same however many
// threads run them.
struct Slabs {
    std::vector<int32_t> owner;  // (N,) a vertex's slab, or -1 (the guard's)
    std::vector<std::vector<int32_t>> visit;  // each slab's vertices, in index order
};

void guard(const int32_t* faces, const uint8_t* alive, int64_t n_faces, const int32_t* vdeg,
           const int32_t* slab, int64_t n_pts, int count, Slabs& out) {
    out.owner.assign(slab, slab + n_pts);
    for (int64_t f = 0; f < n_faces; ++f) {
        if (!alive[f]) continue;
        const int32_t* c = faces + 3 * f;
        if (slab[c[0]] != slab[c[1]] || slab[c[1]] != slab[c[2]])
            out.owner[c[0]] = out.owner[c[1]] = out.owner[c[2]] = -1;
    }
    out.visit.assign(count, {});
    for (int64_t v = 0; v < n_pts; ++v)
        if (vdeg[v] > 0 && out.owner[v] >= 0) out.visit[out.owner[v]].push_back(int32_t(v));
}

}  // namespace

extern "C" {

// Collapse `faces` (n_faces x 3 int32, edited in place; `alive` marks the triangles that
// are left) over `pts` (n_pts x 3 float64, the survivors moved in place) until `target`
// triangles remain or none goes within the bound: stage by stage, each at
// stages[i] x bound_mm, each first slab by slab (`slab`: n_pts int32 in [0, count), on up
// to `threads` threads; count 1: none) and then over the whole mesh, serially, for what
// the slabs left. `locked` (n_pts bytes) never move. Writes the triangles left and the
// last stage's bound (mm), and into counts (6) what the run did: pops tried, pops put
// back at their cost, overlays weighed, collapses to the quadric's point, to w as it was,
// to u. Returns 0, or 1 where it ran out of memory (nothing is then to be used).
int miss_placed_collapse(double* pts, int64_t n_pts, int32_t* faces, int64_t n_faces,
                         uint8_t* alive, const uint8_t* locked, int cap, const double* stages,
                         int n_stages, double bound_mm, double slack, int64_t target,
                         const int32_t* slab, int count, int threads, int64_t* out_alive,
                         double* out_bound, int64_t* counts) try {
    Shared sh;
    sh.vdeg.assign(n_pts, 0);
    for (int64_t f = 0; f < 3 * n_faces; ++f) sh.vdeg[faces[f]] += 1;
    int largest = 0;
    for (int64_t v = 0; v < n_pts; ++v) largest = std::max(largest, sh.vdeg[v]);
    int row = std::max(cap, largest);
    sh.vf.assign(size_t(n_pts) * row, -1);
    std::fill(sh.vdeg.begin(), sh.vdeg.end(), 0);
    for (int64_t f = 0; f < n_faces; ++f)
        for (int c = 0; c < 3; ++c) {
            int32_t u = faces[3 * f + c];
            sh.vf[size_t(u) * row + sh.vdeg[u]++] = int32_t(f);
        }
    sh.q.assign(size_t(n_pts) * 10, 0.0);
    sh.terr.assign(6 * size_t(n_faces), 0.0f);
    sh.need.assign(n_pts, 0.0);
    sh.pos.assign(n_pts, -1);
    sh.via.assign(n_pts, -1);
    threads = std::max(1, std::min(threads, count));
    std::vector<Run> runs(std::max(count, 1));
    for (auto& r : runs) r.attach(pts, faces, alive, locked, n_pts, cap, row, sh);
    runs[0].plane_quadrics(n_faces);
    for (int64_t f = 0; f < n_faces; ++f) alive[f] = 1;
    int64_t n_alive = n_faces;
    double bound = 0.0;
    Slabs slabs;
    for (int i = 0; i < n_stages; ++i) {
        bound = stages[i] * bound_mm + slack;
        if (count > 1 && n_alive > target) {
            guard(faces, alive, n_faces, sh.vdeg.data(), slab, n_pts, count, slabs);
            int64_t total = 0;
            for (auto& v : slabs.visit) total += int64_t(v.size());
            // each slab stops at its share (by vertices) of the triangles to remove
            double share = double(n_alive - target) / double(std::max<int64_t>(total, 1));
            std::vector<int64_t> left(count, n_alive);
            std::atomic<int> failed{0};
            auto work = [&](int first) {
                try {
                    for (int d = first; d < count; d += threads) {
                        Run& r = runs[d];
                        r.owner = slabs.owner.data();
                        r.me = d;
                        int64_t stop = n_alive - int64_t(std::floor(share * slabs.visit[d].size()));
                        left[d] = r.stage(bound, n_alive, stop, slabs.visit[d].data(),
                                          int64_t(slabs.visit[d].size()));
                    }
                } catch (const std::exception&) {
                    failed = 1;
                }
            };
            // (a thread that cannot be started has its slabs run here, after the first's)
            std::vector<std::thread> pool;
            std::vector<int> here = {0};
            for (int t = 1; t < threads; ++t) {
                try {
                    pool.emplace_back(work, t);
                } catch (const std::exception&) {
                    here.push_back(t);
                }
            }
            for (int t : here) work(t);
            for (auto& t : pool) t.join();
            if (failed) return 1;
            int64_t freed = 0;
            for (int d = 0; d < count; ++d) freed += n_alive - left[d];
            n_alive -= freed;
        }
        Run& r = runs[0];
        r.owner = nullptr;
        r.me = 0;
        n_alive = r.stage(bound, n_alive, target, nullptr, n_pts);
        if (n_alive <= target) break;
    }
    for (int k = 0; k < 6; ++k) counts[k] = 0;
    for (auto& r : runs) {
        counts[0] += r.n_tries;
        counts[1] += r.n_rekeyed;
        counts[2] += r.n_overlays;
        for (int k = 0; k < 3; ++k) counts[3 + k] += r.n_spot[k];
    }
    *out_alive = n_alive;
    *out_bound = bound;
    return 0;
} catch (const std::exception&) {  // bad_alloc: an exception must not cross into ctypes
    return 1;
}

}  // extern "C"

static struct PyModuleDef placed_module = {
    PyModuleDef_HEAD_INIT, "_placed", "MISS's placed edge collapse, called through ctypes.", -1,
    nullptr, nullptr, nullptr, nullptr, nullptr};

PyMODINIT_FUNC PyInit__placed(void) { return PyModule_Create(&placed_module); }
