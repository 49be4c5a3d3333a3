// Textures: a material input is either a constant parameter (RGB or scalar) or a bitmap whose
// texels are a parameter too, looked up with Mitsuba's bilinear filtering and wrap modes.
#pragma once

#include <cmath>

#include "math.h"

namespace rbpt {

enum class WrapMode { Repeat, Mirror, Clamp };

struct Bitmap {
    int param = -1;  ///< parameter holding the (height, width, channels) texels, row 0 on top
    int width = 1, height = 1, channels = 3;
    WrapMode wrap = WrapMode::Repeat;
    bool nearest = false;  ///< filter_type "nearest" instead of "bilinear"

    int wrap_index(int i, int n) const {
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
};

/// Mitsuba's mesh_attribute texture: which attribute of the mesh hit it reads.
enum class MeshAttribute { VertexColor = 0, FaceColor = 1 };

/// Reference to a material input: a constant parameter, a bitmap, or a mesh attribute.
struct TextureRef {
    int param = -1;      ///< constant value (when bitmap < 0 and attribute < 0)
    int bitmap = -1;     ///< index into Scene::bitmaps
    int attribute = -1;  ///< a MeshAttribute, read from the shape hit (Shape::attribute_param)
    bool valid() const { return param >= 0 || bitmap >= 0 || attribute >= 0; }
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

/// Evaluate a texture at uv. `P` is the parameter table of the number type S; a bilinear
/// lookup is one call to P::bilinear so that autodiff types can record it as one node.
template <typename S, typename P>
S eval_texture(const TextureRef &tex, const Bitmap *bitmaps, const P &params, Vec2 uv) {
    if (tex.bitmap < 0) return params.spectrum(tex.param);
    const Bitmap &bm = bitmaps[tex.bitmap];
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
    int64_t i0 = bm.wrap_index(int(fx), bm.width), i1 = bm.wrap_index(int(fx) + 1, bm.width);
    int64_t j0 = bm.wrap_index(int(fy), bm.height), j1 = bm.wrap_index(int(fy) + 1, bm.height);
    int64_t index[4] = {j0 * bm.width + i0, j0 * bm.width + i1, j1 * bm.width + i0,
                        j1 * bm.width + i1};
    float weight[4] = {wx0 * wy0, wx1 * wy0, wx0 * wy1, wx1 * wy1};
    return params.bilinear(bm.param, bm.channels, index, weight, 4);
}

}  // namespace rbpt
