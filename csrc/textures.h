// Textures: a material input is either a constant parameter (RGB or scalar) or a texture:
// a bitmap whose texels are a parameter (Mitsuba's bilinear filtering and wrap modes) or a
// checkerboard of two constant parameters. Both map the surface uv through `to_uv` first.
#pragma once

#include <cmath>

#include "math.h"

namespace rbpt {

enum class WrapMode { Repeat, Mirror, Clamp };
enum class TextureType { Bitmap, Checkerboard };

struct Bitmap {
    int param = -1;  ///< parameter holding the (height, width, channels) texels, row 0 on top
    int width = 1, height = 1, channels = 3;
    WrapMode wrap = WrapMode::Repeat;
    bool nearest = false;  ///< filter_type "nearest" instead of "bilinear"

    /// Texel index i wrapped into [0, n).
    RBPT_INLINE int wrap_index(int i, int n) const {
        switch (wrap) {
            case WrapMode::Repeat: { int r = i % n; return r < 0 ? r + n : r; }
            case WrapMode::Clamp: return std::clamp(i, 0, n - 1);
            case WrapMode::Mirror: {
                int period = 2 * n, r = i % period;
                if (r < 0) r += period;
                return r < n ? r : period - 1 - r;
            }
        }
        return 0;
    }
    /// wrap_index(i, n) and wrap_index(i + 1, n), with one integer division (a bilinear
    /// lookup's two neighbours along an axis).
    RBPT_INLINE void wrap_pair(int i, int n, int64_t *w0, int64_t *w1) const {
        if (wrap == WrapMode::Clamp) {
            *w0 = std::clamp(i, 0, n - 1), *w1 = std::clamp(i, -1, n - 2) + 1;
            return;
        }
        const int period = wrap == WrapMode::Repeat ? n : 2 * n;
        int r = i % period;
        r = r < 0 ? r + period : r;
        const int r1 = r + 1 == period ? 0 : r + 1;
        *w0 = r < n ? r : period - 1 - r;  // (mirrored in the period's second half)
        *w1 = r1 < n ? r1 : period - 1 - r1;
    }
};

/// Mitsuba's mesh_attribute texture: which attribute of the mesh hit it reads.
enum class MeshAttribute { VertexColor = 0, FaceColor = 1 };

/// Mitsuba's `checkerboard`: color0 where frac(u) > 1/2 and frac(v) > 1/2 agree, else color1.
struct Checkerboard {
    int color0 = -1, color1 = -1;  ///< constant parameters (RGB or scalar)
};

/// A non-constant material input, tagged by type (dispatched with a switch).
struct Texture {
    TextureType type = TextureType::Bitmap;
    /// Mitsuba's `to_uv`: uv' = M (u, v, 1), the 2D affine part of the XML's 4x4 transform
    /// (rows and columns x, y and translation). Identity: skipped.
    float to_uv[2][3] = {{1.f, 0.f, 0.f}, {0.f, 1.f, 0.f}};
    bool has_to_uv = false;
    Bitmap bitmap;
    Checkerboard checkerboard;

    Vec2 map_uv(Vec2 uv) const {
        if (!has_to_uv) return uv;
        return {to_uv[0][0] * uv.x + to_uv[0][1] * uv.y + to_uv[0][2],
                to_uv[1][0] * uv.x + to_uv[1][1] * uv.y + to_uv[1][2]};
    }
};

/// Reference to a material input: a constant parameter, a texture, or a mesh attribute.
struct TextureRef {
    int param = -1;      ///< constant value (when texture < 0 and attribute < 0)
    int texture = -1;    ///< index into Scene::textures
    int attribute = -1;  ///< a MeshAttribute, read from the shape hit (Shape::attribute_param)
    bool valid() const { return param >= 0 || texture >= 0 || attribute >= 0; }
};

/// A mesh attribute at a hit: a vertex attribute interpolated with the barycentrics (b1, b2)
/// of vertices v[1], v[2] (Mitsuba's eval_attribute), or the attribute of face `face`. The
/// attribute parameter holds `channels` (1 or 3) values per vertex or face; the lookup is one
/// P::bilinear call, so autodiff types record it as one node.
template <typename S, typename P>
S eval_mesh_attribute(MeshAttribute which, int param, int channels, const uint32_t v[3],
                      uint32_t face, float b1, float b2, const P &params) {
    if (which == MeshAttribute::FaceColor) {
        int64_t index[4] = {int64_t(face), 0, 0, 0};
        float weight[4] = {1.f, 0.f, 0.f, 0.f};
        return params.bilinear(param, channels, index, weight, 1);
    }
    int64_t index[4] = {int64_t(v[0]), int64_t(v[1]), int64_t(v[2]), 0};
    float weight[4] = {1.f - b1 - b2, b1, b2, 0.f};
    return params.bilinear(param, channels, index, weight, 3);
}

/// Bitmap lookup at uv. A bilinear lookup is one call to P::bilinear so that autodiff types
/// can record it as one node.
template <typename S, typename P>
S eval_bitmap(const Bitmap &bm, const P &params, Vec2 uv) {
    float x = uv.x * bm.width, y = uv.y * bm.height;
    if (bm.nearest) {
        int64_t i = bm.wrap_index(int(std::floor(x)), bm.width);
        int64_t j = bm.wrap_index(int(std::floor(y)), bm.height);
        int64_t index[4] = {j * bm.width + i, 0, 0, 0};
        float weight[4] = {1.f, 0.f, 0.f, 0.f};
        return params.bilinear(bm.param, bm.channels, index, weight, 1);
    }
    x -= 0.5f;
    y -= 0.5f;
    float fx = std::floor(x), fy = std::floor(y);
    float wx1 = x - fx, wy1 = y - fy, wx0 = 1.f - wx1, wy0 = 1.f - wy1;
    int64_t i0, i1, j0, j1;
    bm.wrap_pair(int(fx), bm.width, &i0, &i1);
    bm.wrap_pair(int(fy), bm.height, &j0, &j1);
    int64_t index[4] = {j0 * bm.width + i0, j0 * bm.width + i1, j1 * bm.width + i0,
                        j1 * bm.width + i1};
    float weight[4] = {wx0 * wy0, wx1 * wy0, wx0 * wy1, wx1 * wy1};
    return params.bilinear(bm.param, bm.channels, index, weight, 4);
}

/// Evaluate a material input at uv. `P` is the parameter table of the number type S.
template <typename S, typename P>
S eval_texture(const TextureRef &ref, const Texture *textures, const P &params, Vec2 uv) {
    if (ref.texture < 0) return params.spectrum(ref.param);
    const Texture &tex = textures[ref.texture];
    uv = tex.map_uv(uv);
    switch (tex.type) {
        case TextureType::Bitmap:
            return eval_bitmap<S>(tex.bitmap, params, uv);
        case TextureType::Checkerboard: {
            bool u_high = uv.x - std::floor(uv.x) > .5f, v_high = uv.y - std::floor(uv.y) > .5f;
            return params.spectrum(u_high == v_high ? tex.checkerboard.color0
                                                    : tex.checkerboard.color1);
        }
    }
    return params.spectrum(ref.param);
}

}  // namespace rbpt
