// The only torch-aware file: argument checks, output allocation, dispatch to the CPU or CUDA launchers
// (csrc/include/rgs/kernels.h), and the pybind11 module `retinexgs._C`.
#include <ATen/Parallel.h>
#include <torch/extension.h>

#include <algorithm>
#include <cstdio>
#include <type_traits>
#include <string>
#include <tuple>
#include <utility>
#include <vector>

#include "rgs/adam.h"
#include "rgs/enhance_loss.h"
#include "rgs/gaussian_colors.h"
#include "rgs/illumination_train.h"
#include "rgs/kernels.h"
#include "rgs/tone.h"
#ifdef RGS_WITH_CUDA
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include "rgs/kernels_cuda.h"
#endif

namespace {

using torch::Tensor;

// Argument errors are raised as pybind11's own ValueError/TypeError rather than c10::Error: on some torch builds
// (seen with torch 2.11 + gcc 13) a c10::Error thrown from an extension crashes the process instead of raising.
// Messages are built without iostreams: on the GPU machine (torch 2.11, gcc 13, pycolmap's wheel loaded in the same
// process) an ostream insertion inside this extension crashed in libstdc++'s locale facets instead of printing.
inline void put(std::string& s, const char* v) { s += v; }
inline void put(std::string& s, const std::string& v) { s += v; }
inline void put(std::string& s, bool v) { s += v ? "true" : "false"; }
template <typename I, std::enable_if_t<std::is_integral_v<I> && !std::is_same_v<I, bool>, int> = 0>
void put(std::string& s, I v) { s += std::to_string(v); }
inline void put(std::string& s, double v) {
    char buf[32];
    std::snprintf(buf, sizeof buf, "%g", v);
    s += buf;
}
inline void put(std::string& s, c10::IntArrayRef v) {
    s += "[";
    for (size_t i = 0; i < v.size(); ++i) s += (i ? ", " : "") + std::to_string(v[i]);
    s += "]";
}
inline void put(std::string& s, c10::ScalarType v) { s += c10::toString(v); }
inline void put(std::string& s, const c10::Device& v) { s += v.str(); }

template <typename... Args>
std::string cat(const Args&... args) {
    std::string s;
    (put(s, args), ...);
    return s;
}
#define RGS_CHECK_VALUE(cond, ...) \
    if (!(cond)) throw pybind11::value_error(cat(__VA_ARGS__))
#define RGS_CHECK_TYPE(cond, ...) \
    if (!(cond)) throw pybind11::type_error(cat(__VA_ARGS__))
// 0: as many threads as torch's intra-op pool (torch.set_num_threads), so the kernels and torch's own ops
// share one thread count, whichever OpenMP runtime torch was built with.
int g_num_threads = 0;

int num_threads() { return g_num_threads > 0 ? g_num_threads : at::get_num_threads(); }

// ---- checks ------------------------------------------------------------------------------------
void check_tensor(const Tensor& t, const char* name, std::vector<int64_t> shape, const Tensor& like) {
    RGS_CHECK_TYPE(t.scalar_type() == like.scalar_type(), name, " must have dtype ", like.scalar_type(),
                     ", got ", t.scalar_type());
    RGS_CHECK_VALUE(t.device() == like.device(), name, " must be on ", like.device(), ", got ", t.device());
    RGS_CHECK_VALUE(t.dim() == int64_t(shape.size()), name, " must have ", shape.size(), " dims, got shape ",
                      t.sizes());
    for (size_t i = 0; i < shape.size(); ++i)
        RGS_CHECK_VALUE(shape[i] < 0 || t.size(i) == shape[i], name, " has shape ", t.sizes(),
                          ", expected size ", shape[i], " at dim ", i);
}

void check_index(const Tensor& t, const char* name, std::vector<int64_t> shape, const Tensor& like) {
    RGS_CHECK_TYPE(t.scalar_type() == torch::kInt32, name, " must be int32, got ", t.scalar_type());
    RGS_CHECK_VALUE(t.device() == like.device(), name, " must be on ", like.device());
    RGS_CHECK_VALUE(t.dim() == int64_t(shape.size()), name, " has shape ", t.sizes());
    for (size_t i = 0; i < shape.size(); ++i)
        RGS_CHECK_VALUE(shape[i] < 0 || t.size(i) == shape[i], name, " has shape ", t.sizes(),
                          ", expected size ", shape[i], " at dim ", i);
}

void check_float(const Tensor& t, const char* name) {
    RGS_CHECK_TYPE(t.scalar_type() == torch::kFloat32 || t.scalar_type() == torch::kFloat64, name,
                     " must be float32 or float64, got ", t.scalar_type());
}

void check_image(int width, int height) {
    RGS_CHECK_VALUE(width > 0 && height > 0, "width and height must be positive, got ", width, "x", height);
}

template <typename T>
rgs::Camera<T> make_camera(const std::vector<double>& viewmat, double fx, double fy, double cx, double cy,
                           int width, int height, double near_plane, double far_plane) {
    RGS_CHECK_VALUE(viewmat.size() == 16, "viewmat must have 16 entries, got ", viewmat.size());
    for (double v : viewmat) RGS_CHECK_VALUE(std::isfinite(v), "viewmat must be finite");
    RGS_CHECK_VALUE(std::isfinite(fx) && std::isfinite(fy) && fx > 0 && fy > 0,
                      "fx and fy must be finite and positive, got ", fx, ", ", fy);
    RGS_CHECK_VALUE(std::isfinite(cx) && std::isfinite(cy), "cx and cy must be finite, got ", cx, ", ", cy);
    RGS_CHECK_VALUE(near_plane > 0 && far_plane > near_plane, "need 0 < near < far, got ", near_plane, ", ",
                      far_plane);
    check_image(width, height);
    rgs::Camera<T> cam;
    for (int i = 0; i < 16; ++i) cam.viewmat[i] = T(viewmat[i]);
    cam.fx = T(fx);
    cam.fy = T(fy);
    cam.cx = T(cx);
    cam.cy = T(cy);
    cam.width = width;
    cam.height = height;
    cam.near_plane = T(near_plane);
    cam.far_plane = T(far_plane);
    return cam;
}

#ifdef RGS_WITH_CUDA
#define RGS_CUDA_STREAM(t) (at::cuda::getCurrentCUDAStream((t).device().index()).stream())
#define RGS_DEVICE_GUARD(t) \
    const at::cuda::OptionalCUDAGuard device_guard((t).is_cuda() ? std::optional<at::Device>((t).device()) : std::nullopt)
#else
#define RGS_DEVICE_GUARD(t) ((void)0)
#endif

#ifdef RGS_WITH_CUDA
// Scratch memory for the CUDA launchers, from torch's caching allocator; released when the call returns
// (safe: later work on the same stream is ordered after the kernels that use it).
struct TorchScratch {
    std::vector<Tensor> buffers;
    torch::Device device;
};

void* scratch_alloc(size_t bytes, void* ctx) {
    auto* s = static_cast<TorchScratch*>(ctx);
    s->buffers.push_back(torch::empty({int64_t(bytes > 0 ? bytes : 1)},
                                      torch::TensorOptions().dtype(torch::kUInt8).device(s->device)));
    return s->buffers.back().data_ptr();
}

// capacity < 0: M read back to the host (one sync), gauss_ids [M]. capacity >= 0: no sync; gauss_ids [capacity],
// M written into count (int64 [1]) on the device.
template <typename scalar_t>
Tensor rgs_bin_gaussians_cuda(const Tensor& means2d, const Tensor& radii, const scalar_t* conics,
                              const scalar_t* opacities, const Tensor& depths, rgs::TileGrid grid,
                              Tensor& tile_ranges, int64_t capacity, int64_t* count) {
    const int64_t N = means2d.size(0);
    TorchScratch scratch{{}, means2d.device()};
    const rgs::DeviceAllocator alloc{scratch_alloc, &scratch};
    auto stream = RGS_CUDA_STREAM(means2d);
    Tensor offsets = torch::empty({N > 0 ? N : 1}, means2d.options().dtype(torch::kInt64));
    const bool sync_free = capacity >= 0;
    int64_t M = rgs::count_tile_pairs_cuda<scalar_t>(N, means2d.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(),
                                                     conics, opacities, grid, offsets.data_ptr<int64_t>(), alloc,
                                                     stream, sync_free ? count : nullptr);
    if (sync_free) M = capacity;  // checked against int32 by the caller
    RGS_CHECK_VALUE(M < (int64_t(1) << 31), "too many tile/Gaussian pairs (", M, ") for int32 indices");
    Tensor gauss_ids = torch::empty({M}, means2d.options().dtype(torch::kInt32));
    rgs::bin_tile_pairs_cuda<scalar_t>(N, means2d.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(), conics, opacities,
                                       depths.data_ptr<scalar_t>(), grid, offsets.data_ptr<int64_t>(), M,
                                       sync_free ? count : nullptr, gauss_ids.data_ptr<int32_t>(),
                                       tile_ranges.data_ptr<int32_t>(), alloc, stream);
    return gauss_ids;
}
#endif

[[noreturn]] void no_cuda() {
    throw pybind11::value_error("retinexgs._C was built without CUDA kernels; reinstall with a CUDA build of "
                                "torch and a CUDA toolkit, or pass CPU tensors");
}

// ---- projection --------------------------------------------------------------------------------
// check_finite: also report whether the render inputs are finite (rgs::FiniteCheck) as a 5th output, int32 [1]
// (0: all finite), with colors [N, C] and background [C] (optional) checked beside the projection's own inputs;
// without it the 5th output is None. The caller reads the flag where it synchronises anyway.
std::tuple<Tensor, Tensor, Tensor, Tensor, Tensor> project_forward(
    Tensor means, Tensor quats, Tensor scales, Tensor opacities, std::vector<double> viewmat, double fx, double fy,
    double cx, double cy, int width, int height, double near_plane, double far_plane, bool check_finite,
    std::optional<Tensor> colors_opt, std::optional<Tensor> background_opt) {
    check_float(means, "means");
    const int64_t N = means.size(0);
    check_tensor(means, "means", {N, 3}, means);
    check_tensor(quats, "quats", {N, 4}, means);
    check_tensor(scales, "scales", {N, 3}, means);
    check_tensor(opacities, "opacities", {N}, means);
    RGS_CHECK_VALUE(check_finite || (!colors_opt.has_value() && !background_opt.has_value()),
                    "colors and background are only read by the finiteness check (check_finite=True)");
    RGS_CHECK_VALUE(!background_opt.has_value() || colors_opt.has_value(), "a background needs colors");
    Tensor colors, background, flag;
    if (colors_opt.has_value()) {
        RGS_CHECK_VALUE(colors_opt->dim() == 2, "colors must have shape (N, C)");
        check_tensor(*colors_opt, "colors", {N, colors_opt->size(1)}, means);
        colors = colors_opt->contiguous();
    }
    if (background_opt.has_value()) {
        check_tensor(*background_opt, "background", {colors.size(1)}, means);
        background = background_opt->contiguous();
    }
    means = means.contiguous(), quats = quats.contiguous(), scales = scales.contiguous();
    opacities = opacities.contiguous();
    auto opts = means.options();
    Tensor means2d = torch::empty({N, 2}, opts), depths = torch::empty({N}, opts);
    Tensor conics = torch::empty({N, 3}, opts);
    Tensor radii = torch::empty({N, 2}, opts.dtype(torch::kInt32));
    if (check_finite) flag = torch::zeros({1}, opts.dtype(torch::kInt32));
    RGS_DEVICE_GUARD(means);
    AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_forward", [&] {
        auto cam = make_camera<scalar_t>(viewmat, fx, fy, cx, cy, width, height, near_plane, far_plane);
        rgs::FiniteCheck<scalar_t> check;
        if (check_finite) {
            check.flag = flag.data_ptr<int32_t>();
            if (colors.defined()) check.colors = colors.data_ptr<scalar_t>(), check.channels = colors.size(1);
            if (background.defined()) check.background = background.data_ptr<scalar_t>();
        }
        if (means.is_cuda()) {
#ifdef RGS_WITH_CUDA
            rgs::project_forward_cuda<scalar_t>(N, means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(),
                                                scales.data_ptr<scalar_t>(), opacities.data_ptr<scalar_t>(), cam,
                                                means2d.data_ptr<scalar_t>(), depths.data_ptr<scalar_t>(),
                                                conics.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(), check,
                                                RGS_CUDA_STREAM(means));
#else
            no_cuda();
#endif
        } else {
            rgs::project_forward_cpu<scalar_t>(N, means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(),
                                               scales.data_ptr<scalar_t>(), opacities.data_ptr<scalar_t>(), cam,
                                               means2d.data_ptr<scalar_t>(), depths.data_ptr<scalar_t>(),
                                               conics.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(), check,
                                               num_threads());
        }
    });
    return {means2d, depths, conics, radii, flag};
}

std::tuple<Tensor, Tensor, Tensor> project_backward(Tensor means, Tensor quats, Tensor scales,
                                                    std::vector<double> viewmat, double fx, double fy, double cx,
                                                    double cy, int width, int height, double near_plane,
                                                    double far_plane, Tensor radii, Tensor v_means2d,
                                                    Tensor v_depths, Tensor v_conics) {
    check_float(means, "means");
    const int64_t N = means.size(0);
    check_tensor(means, "means", {N, 3}, means);
    check_tensor(quats, "quats", {N, 4}, means);
    check_tensor(scales, "scales", {N, 3}, means);
    check_index(radii, "radii", {N, 2}, means);
    check_tensor(v_means2d, "v_means2d", {N, 2}, means);
    check_tensor(v_depths, "v_depths", {N}, means);
    check_tensor(v_conics, "v_conics", {N, 3}, means);
    means = means.contiguous(), quats = quats.contiguous(), scales = scales.contiguous();
    radii = radii.contiguous(), v_means2d = v_means2d.contiguous(), v_depths = v_depths.contiguous();
    v_conics = v_conics.contiguous();
    Tensor v_means = torch::empty_like(means), v_quats = torch::empty_like(quats);
    Tensor v_scales = torch::empty_like(scales);
    RGS_DEVICE_GUARD(means);
    AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_backward", [&] {
        auto cam = make_camera<scalar_t>(viewmat, fx, fy, cx, cy, width, height, near_plane, far_plane);
        if (means.is_cuda()) {
#ifdef RGS_WITH_CUDA
            rgs::project_backward_cuda<scalar_t>(
                N, means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(), scales.data_ptr<scalar_t>(), cam,
                radii.data_ptr<int32_t>(), v_means2d.data_ptr<scalar_t>(), v_depths.data_ptr<scalar_t>(),
                v_conics.data_ptr<scalar_t>(), v_means.data_ptr<scalar_t>(), v_quats.data_ptr<scalar_t>(),
                v_scales.data_ptr<scalar_t>(), RGS_CUDA_STREAM(means));
#else
            no_cuda();
#endif
        } else {
            rgs::project_backward_cpu<scalar_t>(
                N, means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(), scales.data_ptr<scalar_t>(), cam,
                radii.data_ptr<int32_t>(), v_means2d.data_ptr<scalar_t>(), v_depths.data_ptr<scalar_t>(),
                v_conics.data_ptr<scalar_t>(), v_means.data_ptr<scalar_t>(), v_quats.data_ptr<scalar_t>(),
                v_scales.data_ptr<scalar_t>(), num_threads());
        }
    });
    return {v_means, v_quats, v_scales};
}

// ---- tile binning ------------------------------------------------------------------------------
// conics [N, 3] and opacities [N] (both or neither): a Gaussian pairs only with the tiles of its rectangle that it
// can reach (rgs::TileReach); they must be the ones the compositing gets, or it could miss a pair.
// capacity >= 0 (with count, int64 [1] on the same device): no host sync on the GPU; gauss_ids [capacity], the pair
// count M written into count; pairs at offsets >= capacity dropped (the highest-index Gaussians'), ranges cover
// min(M, capacity) pairs, the ids past them are -1. The CPU computes the same (M on the host: it pays no sync).
std::tuple<Tensor, Tensor> bin_gaussians(Tensor means2d, Tensor radii, Tensor depths, int width, int height,
                                         std::optional<Tensor> conics_opt, std::optional<Tensor> opacities_opt,
                                         int64_t capacity, std::optional<Tensor> count_opt) {
    check_float(means2d, "means2d");
    check_image(width, height);
    const int64_t N = means2d.size(0);
    check_tensor(means2d, "means2d", {N, 2}, means2d);
    check_index(radii, "radii", {N, 2}, means2d);
    check_tensor(depths, "depths", {N}, means2d);
    RGS_CHECK_VALUE(conics_opt.has_value() == opacities_opt.has_value(),
                    "pass both conics and opacities to bin_gaussians, or neither");
    const bool cull = conics_opt.has_value();
    Tensor conics, opacities;
    if (cull) {
        check_tensor(*conics_opt, "conics", {N, 3}, means2d);
        check_tensor(*opacities_opt, "opacities", {N}, means2d);
        conics = conics_opt->contiguous(), opacities = opacities_opt->contiguous();
    }
    const bool sync_free = capacity >= 0;
    RGS_CHECK_VALUE(!sync_free || count_opt.has_value(), "bin_gaussians with a capacity needs count");
    RGS_CHECK_VALUE(capacity < (int64_t(1) << 31), "capacity ", capacity, " is too large for int32 indices");
    Tensor count;
    if (sync_free) {
        count = *count_opt;
        RGS_CHECK_TYPE(count.scalar_type() == torch::kInt64, "count must be int64, got ", count.scalar_type());
        RGS_CHECK_VALUE(count.device() == means2d.device(), "count must be on ", means2d.device());
        RGS_CHECK_VALUE(count.numel() == 1 && count.is_contiguous(), "count must be a contiguous [1] tensor");
    }
    means2d = means2d.contiguous(), radii = radii.contiguous(), depths = depths.contiguous();
    const rgs::TileGrid grid = rgs::make_tile_grid(width, height);
    auto iopts = means2d.options().dtype(torch::kInt32);
    Tensor tile_ranges = torch::empty({grid.count(), 2}, iopts);
    Tensor gauss_ids;
    RGS_DEVICE_GUARD(means2d);
    AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "bin_gaussians", [&] {
        const scalar_t* conics_p = cull ? conics.data_ptr<scalar_t>() : nullptr;
        const scalar_t* opacities_p = cull ? opacities.data_ptr<scalar_t>() : nullptr;
        if (means2d.is_cuda()) {
#ifdef RGS_WITH_CUDA
            gauss_ids = rgs_bin_gaussians_cuda<scalar_t>(means2d, radii, conics_p, opacities_p, depths, grid,
                                                         tile_ranges, capacity,
                                                         sync_free ? count.data_ptr<int64_t>() : nullptr);
#else
            no_cuda();
#endif
        } else {
            Tensor offsets = torch::empty({N + 1}, means2d.options().dtype(torch::kInt64));
            const int64_t M = rgs::count_tile_pairs_cpu<scalar_t>(N, means2d.data_ptr<scalar_t>(),
                                                                  radii.data_ptr<int32_t>(), conics_p, opacities_p,
                                                                  grid, offsets.data_ptr<int64_t>(), num_threads());
            RGS_CHECK_VALUE(sync_free || M < (int64_t(1) << 31), "too many tile/Gaussian pairs (", M,
                            ") for int32 indices");
            const int64_t stored = sync_free ? std::min(M, capacity) : M;
            gauss_ids = torch::empty({sync_free ? capacity : M}, iopts);
            rgs::bin_tile_pairs_cpu<scalar_t>(N, means2d.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(), conics_p,
                                              opacities_p, depths.data_ptr<scalar_t>(), grid,
                                              offsets.data_ptr<int64_t>(), stored,
                                              gauss_ids.data_ptr<int32_t>(), tile_ranges.data_ptr<int32_t>(),
                                              num_threads());
            if (sync_free) {
                gauss_ids.narrow(0, stored, capacity - stored).fill_(-1);  // padding, as the GPU writes it
                count.fill_(M);
            }
        }
    });
    return {gauss_ids, tile_ranges};
}

// ---- compositing -------------------------------------------------------------------------------
void check_raster_inputs(const Tensor& means2d, const Tensor& conics, const Tensor& colors, const Tensor& opacities,
                         const Tensor& gauss_ids, const Tensor& tile_ranges, int width, int height) {
    check_float(means2d, "means2d");
    check_image(width, height);
    const int64_t N = means2d.size(0);
    check_tensor(means2d, "means2d", {N, 2}, means2d);
    check_tensor(conics, "conics", {N, 3}, means2d);
    check_tensor(colors, "colors", {N, -1}, means2d);
    RGS_CHECK_VALUE(colors.size(1) >= 1, "colors must have at least one channel");
    check_tensor(opacities, "opacities", {N}, means2d);
    check_index(gauss_ids, "gauss_ids", {-1}, means2d);
    check_index(tile_ranges, "tile_ranges", {rgs::make_tile_grid(width, height).count(), 2}, means2d);
#ifdef RGS_WITH_CUDA
    RGS_CHECK_VALUE(!means2d.is_cuda() || colors.size(1) <= rgs::kMaxCudaChannels, "colors has ", colors.size(1),
                      " channels; the CUDA compositing supports at most ", rgs::kMaxCudaChannels);
#endif
}

// The output layout of a render (rgs/types.h OutputLayout): background [n_bg <= C] on the leading channels, alpha as
// one more channel. The background is checked against the colours' dtype and device.
template <typename T>
static rgs::OutputLayout<T> output_layout(int C, const std::optional<Tensor>& background, bool alpha) {
    rgs::OutputLayout<T> layout;
    layout.C = C;
    layout.alpha = alpha;
    if (background) {
        layout.n_bg = int(background->size(0));
        layout.bg = background->data_ptr<T>();
    }
    return layout;
}

static Tensor check_background(const std::optional<Tensor>& background, const Tensor& colors, const Tensor& like) {
    RGS_CHECK_VALUE(background->dim() == 1 && background->size(0) >= 1 && background->size(0) <= colors.size(1),
                    "background must be [K] with 1 <= K <= colors' ", colors.size(1), " channels, got ",
                    background->sizes());
    check_tensor(*background, "background", {background->size(0)}, like);
    return background->contiguous();
}

std::tuple<Tensor, Tensor, Tensor> rasterize_forward(Tensor means2d, Tensor conics, Tensor colors,
                                                     Tensor opacities, Tensor gauss_ids, Tensor tile_ranges,
                                                     int width, int height, std::optional<Tensor> background,
                                                     bool alpha) {
    check_raster_inputs(means2d, conics, colors, opacities, gauss_ids, tile_ranges, width, height);
    if (background) background = check_background(background, colors, means2d);
    means2d = means2d.contiguous(), conics = conics.contiguous(), colors = colors.contiguous();
    opacities = opacities.contiguous(), gauss_ids = gauss_ids.contiguous(), tile_ranges = tile_ranges.contiguous();
    const int64_t N = means2d.size(0);
    const int C = int(colors.size(1));
    auto opts = means2d.options();
    Tensor image = torch::empty({height, width, C + (alpha ? 1 : 0)}, opts);
    Tensor transmittance = torch::empty({height, width}, opts);
    Tensor last_ids = torch::empty({height, width}, opts.dtype(torch::kInt32));
    RGS_DEVICE_GUARD(means2d);
    AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "rasterize_forward", [&] {
        const auto layout = output_layout<scalar_t>(C, background, alpha);
        if (means2d.is_cuda()) {
#ifdef RGS_WITH_CUDA
            rgs::rasterize_forward_cuda<scalar_t>(
                N, layout, width, height, means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
                colors.data_ptr<scalar_t>(), opacities.data_ptr<scalar_t>(), gauss_ids.data_ptr<int32_t>(),
                tile_ranges.data_ptr<int32_t>(), image.data_ptr<scalar_t>(), transmittance.data_ptr<scalar_t>(),
                last_ids.data_ptr<int32_t>(), RGS_CUDA_STREAM(means2d));
#else
            no_cuda();
#endif
        } else {
            rgs::rasterize_forward_cpu<scalar_t>(
                N, layout, width, height, means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
                colors.data_ptr<scalar_t>(), opacities.data_ptr<scalar_t>(), gauss_ids.data_ptr<int32_t>(),
                tile_ranges.data_ptr<int32_t>(), image.data_ptr<scalar_t>(), transmittance.data_ptr<scalar_t>(),
                last_ids.data_ptr<int32_t>(), num_threads());
        }
    });
    return {image, transmittance, last_ids};
}

std::tuple<Tensor, Tensor, Tensor, Tensor> rasterize_backward(Tensor means2d, Tensor conics, Tensor colors,
                                                              Tensor opacities, Tensor gauss_ids,
                                                              Tensor tile_ranges, int width, int height,
                                                              Tensor transmittance, Tensor last_ids,
                                                              Tensor v_image, std::optional<Tensor> v_transmittance,
                                                              std::optional<Tensor> background, bool alpha) {
    check_raster_inputs(means2d, conics, colors, opacities, gauss_ids, tile_ranges, width, height);
    const int64_t N = means2d.size(0);
    const int C = int(colors.size(1));
    check_tensor(transmittance, "transmittance", {height, width}, means2d);
    check_index(last_ids, "last_ids", {height, width}, means2d);
    if (background) background = check_background(background, colors, means2d);
    check_tensor(v_image, "v_image", {height, width, C + (alpha ? 1 : 0)}, means2d);
    if (v_transmittance) {
        check_tensor(*v_transmittance, "v_transmittance", {height, width}, means2d);
        v_transmittance = v_transmittance->contiguous();
    }
    means2d = means2d.contiguous(), conics = conics.contiguous(), colors = colors.contiguous();
    opacities = opacities.contiguous(), gauss_ids = gauss_ids.contiguous(), tile_ranges = tile_ranges.contiguous();
    transmittance = transmittance.contiguous(), last_ids = last_ids.contiguous();
    v_image = v_image.contiguous();
    // The CUDA kernel accumulates with atomics into zeroed buffers; the CPU kernel writes every entry.
    auto make = [&](const Tensor& t) { return means2d.is_cuda() ? torch::zeros_like(t) : torch::empty_like(t); };
    Tensor v_means2d = make(means2d), v_conics = make(conics), v_colors = make(colors), v_opacities = make(opacities);
    const int64_t M = gauss_ids.size(0);
    RGS_DEVICE_GUARD(means2d);
    AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "rasterize_backward", [&] {
        const auto layout = output_layout<scalar_t>(C, background, alpha);
        const scalar_t* v_T = v_transmittance ? v_transmittance->data_ptr<scalar_t>() : nullptr;
        if (means2d.is_cuda()) {
#ifdef RGS_WITH_CUDA
            rgs::rasterize_backward_cuda<scalar_t>(
                N, layout, width, height, means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
                colors.data_ptr<scalar_t>(), opacities.data_ptr<scalar_t>(), gauss_ids.data_ptr<int32_t>(),
                tile_ranges.data_ptr<int32_t>(), M, transmittance.data_ptr<scalar_t>(),
                last_ids.data_ptr<int32_t>(), v_image.data_ptr<scalar_t>(), v_T,
                v_means2d.data_ptr<scalar_t>(), v_conics.data_ptr<scalar_t>(), v_colors.data_ptr<scalar_t>(),
                v_opacities.data_ptr<scalar_t>(), RGS_CUDA_STREAM(means2d));
#else
            no_cuda();
#endif
        } else {
            rgs::rasterize_backward_cpu<scalar_t>(
                N, layout, width, height, means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
                colors.data_ptr<scalar_t>(), opacities.data_ptr<scalar_t>(), gauss_ids.data_ptr<int32_t>(),
                tile_ranges.data_ptr<int32_t>(), M, transmittance.data_ptr<scalar_t>(),
                last_ids.data_ptr<int32_t>(), v_image.data_ptr<scalar_t>(), v_T,
                v_means2d.data_ptr<scalar_t>(), v_conics.data_ptr<scalar_t>(), v_colors.data_ptr<scalar_t>(),
                v_opacities.data_ptr<scalar_t>(), num_threads());
        }
    });
    return {v_means2d, v_conics, v_colors, v_opacities};
}

// ---- spherical harmonics -----------------------------------------------------------------------
void check_sh_inputs(int degree, const Tensor& dirs, const Tensor& coeffs) {
    check_float(coeffs, "coeffs");
    RGS_CHECK_VALUE(degree >= 0 && degree <= 3, "sh degree must be in 0..3, got ", degree);
    const int64_t N = coeffs.size(0);
    check_tensor(coeffs, "coeffs", {N, -1, -1}, coeffs);
    RGS_CHECK_VALUE(coeffs.size(1) >= (degree + 1) * (degree + 1), "coeffs has ", coeffs.size(1),
                      " bases, degree ", degree, " needs ", (degree + 1) * (degree + 1));
    check_tensor(dirs, "dirs", {N, 3}, coeffs);
}

Tensor sh_forward(int degree, Tensor dirs, Tensor coeffs) {
    check_sh_inputs(degree, dirs, coeffs);
    dirs = dirs.contiguous(), coeffs = coeffs.contiguous();
    const int64_t N = coeffs.size(0);
    const int K = int(coeffs.size(1)), D = int(coeffs.size(2));
    Tensor colors = torch::empty({N, D}, coeffs.options());
    RGS_DEVICE_GUARD(coeffs);
    AT_DISPATCH_FLOATING_TYPES(coeffs.scalar_type(), "sh_forward", [&] {
        if (coeffs.is_cuda()) {
#ifdef RGS_WITH_CUDA
            rgs::sh_forward_cuda<scalar_t>(N, degree, K, D, dirs.data_ptr<scalar_t>(), coeffs.data_ptr<scalar_t>(),
                                           colors.data_ptr<scalar_t>(), RGS_CUDA_STREAM(coeffs));
#else
            no_cuda();
#endif
        } else {
            rgs::sh_forward_cpu<scalar_t>(N, degree, K, D, dirs.data_ptr<scalar_t>(), coeffs.data_ptr<scalar_t>(),
                                          colors.data_ptr<scalar_t>(), num_threads());
        }
    });
    return colors;
}

std::tuple<Tensor, Tensor> sh_backward(int degree, Tensor dirs, Tensor coeffs, Tensor v_colors) {
    check_sh_inputs(degree, dirs, coeffs);
    const int64_t N = coeffs.size(0);
    const int K = int(coeffs.size(1)), D = int(coeffs.size(2));
    check_tensor(v_colors, "v_colors", {N, D}, coeffs);
    dirs = dirs.contiguous(), coeffs = coeffs.contiguous(), v_colors = v_colors.contiguous();
    Tensor v_dirs = torch::empty_like(dirs), v_coeffs = torch::empty_like(coeffs);
    RGS_DEVICE_GUARD(coeffs);
    AT_DISPATCH_FLOATING_TYPES(coeffs.scalar_type(), "sh_backward", [&] {
        if (coeffs.is_cuda()) {
#ifdef RGS_WITH_CUDA
            rgs::sh_backward_cuda<scalar_t>(N, degree, K, D, dirs.data_ptr<scalar_t>(),
                                            coeffs.data_ptr<scalar_t>(), v_colors.data_ptr<scalar_t>(),
                                            v_dirs.data_ptr<scalar_t>(), v_coeffs.data_ptr<scalar_t>(),
                                            RGS_CUDA_STREAM(coeffs));
#else
            no_cuda();
#endif
        } else {
            rgs::sh_backward_cpu<scalar_t>(N, degree, K, D, dirs.data_ptr<scalar_t>(), coeffs.data_ptr<scalar_t>(),
                                           v_colors.data_ptr<scalar_t>(), v_dirs.data_ptr<scalar_t>(),
                                           v_coeffs.data_ptr<scalar_t>(), num_threads());
        }
    });
    return {v_dirs, v_coeffs};
}

// ---- per-Gaussian colours of a trained scene (inference) ---------------------------------------
rgs::IllumConfig make_illum_config(int pos_freqs, int dir_freqs, int hidden, int depth, int dir_hidden) {
    RGS_CHECK_VALUE(pos_freqs >= 0 && pos_freqs <= rgs::kMaxIllumFreqs && dir_freqs >= 0 &&
                        dir_freqs <= rgs::kMaxIllumFreqs,
                    "illumination pos_freqs and dir_freqs must be in 0..", rgs::kMaxIllumFreqs, ", got ", pos_freqs,
                    " and ", dir_freqs);
    RGS_CHECK_VALUE(hidden >= 1 && hidden <= rgs::kMaxIllumWidth && dir_hidden >= 1 &&
                        dir_hidden <= rgs::kMaxIllumWidth,
                    "the fused colour kernel supports illumination hidden and dir_hidden widths 1..",
                    rgs::kMaxIllumWidth, ", got hidden=", hidden, ", dir_hidden=", dir_hidden);
    RGS_CHECK_VALUE(depth >= 1 && depth <= 64, "illumination depth must be in 1..64, got ", depth);
    return rgs::IllumConfig{pos_freqs, dir_freqs, hidden, depth, dir_hidden};
}

// Packs the illumination MLP's Linear weights ([out, in]) and biases ([out]) in rgs::illum_layout order: trunk
// layers, then the head's two layers. Returns one flat buffer of the weights' dtype and device.
Tensor pack_illum_weights(std::vector<Tensor> weights, std::vector<Tensor> biases, int pos_freqs, int dir_freqs,
                          int hidden, int depth, int dir_hidden) {
    const rgs::IllumConfig cfg = make_illum_config(pos_freqs, dir_freqs, hidden, depth, dir_hidden);
    const size_t layers = size_t(depth) + 2;
    RGS_CHECK_VALUE(weights.size() == layers && biases.size() == layers, "expected ", layers,
                    " weights and biases (depth + 2 Linear layers), got ", weights.size(), " and ", biases.size());
    const rgs::IllumLayout L = rgs::illum_layout(cfg);
    check_float(weights[0], "weights[0]");
    Tensor flat = torch::zeros({L.total}, weights[0].options());
    auto put = [&](size_t l, int64_t in, int64_t out, int64_t w_at, int64_t b_at) {
        const std::string wn = cat("weights[", l, "]"), bn = cat("biases[", l, "]");
        check_tensor(weights[l], wn.c_str(), {out, in}, flat);
        check_tensor(biases[l], bn.c_str(), {out}, flat);
        flat.narrow(0, w_at, in * out).view({in, out}).copy_(weights[l].detach().t());
        flat.narrow(0, b_at, out).copy_(biases[l].detach());
    };
    put(0, rgs::encoded_width(pos_freqs), hidden, L.trunk0_w, L.trunk0_b);
    for (int l = 1; l < depth; ++l)
        put(size_t(l), hidden, hidden, L.trunk_w + (l - 1) * L.trunk_stride, L.trunk_b + (l - 1) * L.trunk_stride);
    put(size_t(depth), hidden + rgs::encoded_width(dir_freqs), dir_hidden, L.head0_w, L.head0_b);
    put(size_t(depth) + 1, dir_hidden, 3, L.head1_w, L.head1_b);
    return flat;
}

// [N, 3] reflectance max(SH(means - center) + 0.5, 0), or [N, 6] with the illumination MLP when `illum`
// (pos_freqs, dir_freqs, hidden, depth, dir_hidden) and its packed `weights` are given.
Tensor gaussian_colors(int degree, Tensor means, Tensor sh_dc, Tensor sh_rest, std::vector<double> center,
                       std::optional<std::vector<int>> illum, double bound, std::optional<Tensor> weights) {
    check_float(means, "means");
    RGS_CHECK_VALUE(degree >= 0 && degree <= 3, "sh degree must be in 0..3, got ", degree);
    const int64_t N = means.size(0);
    check_tensor(means, "means", {N, 3}, means);
    check_tensor(sh_dc, "sh_dc", {N, 1, 3}, means);
    check_tensor(sh_rest, "sh_rest", {N, -1, 3}, means);
    const int rest = int(sh_rest.size(1));
    RGS_CHECK_VALUE(rest + 1 >= (degree + 1) * (degree + 1), "sh_rest has ", rest, " bases, degree ", degree,
                    " needs ", (degree + 1) * (degree + 1) - 1);
    RGS_CHECK_VALUE(center.size() == 3, "center must have 3 entries, got ", center.size());
    for (double c : center) RGS_CHECK_VALUE(std::isfinite(c), "center must be finite");
    RGS_CHECK_VALUE(illum.has_value() == weights.has_value(), "pass both the illumination shape and its weights, "
                    "or neither");
    rgs::IllumConfig cfg{0, 0, 0, 1, 0};
    if (illum) {
        RGS_CHECK_VALUE(illum->size() == 5, "illum must be (pos_freqs, dir_freqs, hidden, depth, dir_hidden), got ",
                        illum->size(), " values");
        cfg = make_illum_config((*illum)[0], (*illum)[1], (*illum)[2], (*illum)[3], (*illum)[4]);
        RGS_CHECK_VALUE(std::isfinite(bound) && bound > 0, "illumination bound must be finite and positive, got ",
                        bound);
        const int64_t total = rgs::illum_layout(cfg).total;
        check_tensor(*weights, "weights", {total}, means);
        RGS_CHECK_VALUE(weights->is_contiguous() && reinterpret_cast<uintptr_t>(weights->data_ptr()) % 16 == 0,
                        "weights must be contiguous and 16-byte aligned (use pack_illum_weights)");
    }
    means = means.contiguous(), sh_dc = sh_dc.contiguous(), sh_rest = sh_rest.contiguous();
    const int C = illum ? 6 : 3;
    Tensor colors = torch::empty({N, C}, means.options());
    RGS_DEVICE_GUARD(means);
    AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "gaussian_colors", [&] {
        const scalar_t c[3] = {scalar_t(center[0]), scalar_t(center[1]), scalar_t(center[2])};
        const rgs::IllumConfig* icfg = illum ? &cfg : nullptr;
        const scalar_t* w = illum ? weights->data_ptr<scalar_t>() : nullptr;
        if (means.is_cuda()) {
#ifdef RGS_WITH_CUDA
            rgs::gaussian_colors_cuda<scalar_t>(N, degree, rest, means.data_ptr<scalar_t>(),
                                                sh_dc.data_ptr<scalar_t>(), sh_rest.data_ptr<scalar_t>(), c, icfg,
                                                bound, w, colors.data_ptr<scalar_t>(), RGS_CUDA_STREAM(means));
#else
            no_cuda();
#endif
        } else {
            rgs::gaussian_colors_cpu<scalar_t>(N, degree, rest, means.data_ptr<scalar_t>(),
                                               sh_dc.data_ptr<scalar_t>(), sh_rest.data_ptr<scalar_t>(), c, icfg,
                                               bound, w, colors.data_ptr<scalar_t>(), num_threads());
        }
    });
    return colors;
}

// ---- the illumination field's MLP in training (rgs/illumination_train.h) ------------------------------------
rgs::IllumConfig train_illum_config(const std::vector<int>& illum) {
    RGS_CHECK_VALUE(illum.size() == 5, "illum must be (pos_freqs, dir_freqs, hidden, depth, dir_hidden), got ",
                    illum.size(), " values");
    const rgs::IllumConfig cfg = make_illum_config(illum[0], illum[1], illum[2], illum[3], illum[4]);
    RGS_CHECK_VALUE(cfg.depth + 2 <= rgs::kMaxTrainLayers, "the training kernels support an illumination depth up to ",
                    rgs::kMaxTrainLayers - 2, ", got ", cfg.depth);
    return cfg;
}

// (in, out, a_in, d_out, (a_width, d_width)) of each Linear layer: the rows of A and D (IllumTrainLayout).
std::vector<std::vector<int>> illumination_train_layout(std::vector<int> illum) {
    const rgs::IllumTrainLayout S = rgs::illum_train_layout(train_illum_config(illum));
    std::vector<std::vector<int>> out(5);
    for (int l = 0; l < S.layers; ++l) {
        out[0].push_back(S.in[l]);
        out[1].push_back(S.out[l]);
        out[2].push_back(S.a_in[l]);
        out[3].push_back(S.d_out[l]);
    }
    out[4] = {S.a_width, S.d_width};
    return out;
}

void check_illum_inputs(const Tensor& means, const Tensor& center, const rgs::IllumConfig& cfg, double bound,
                        const Tensor& weights) {
    check_float(means, "means");
    check_tensor(means, "means", {means.size(0), 3}, means);
    check_tensor(center, "center", {3}, means);
    RGS_CHECK_VALUE(std::isfinite(bound) && bound > 0, "illumination bound must be finite and positive, got ", bound);
    check_tensor(weights, "weights", {rgs::illum_layout(cfg).total}, means);
    RGS_CHECK_VALUE(weights.is_contiguous() && reinterpret_cast<uintptr_t>(weights.data_ptr()) % 16 == 0,
                    "weights must be contiguous and 16-byte aligned (use pack_illum_weights)");
}

// The columns of A and D for N Gaussians: N rounded up to whole chunks of kIllumChunk, so that a layer's weight
// gradient is one batched product over the chunks and a sum (cuBLAS gives one N-long product of these thin matrices
// few blocks: 41 µs a layer at 58k Gaussians on an H200).
constexpr int64_t kIllumChunk = 1024;
int64_t illum_columns(int64_t N) { return (N + kIllumChunk - 1) / kIllumChunk * kIllumChunk; }

// (rgb [N, 3], A [a_width, illum_columns(N)]): IlluminationField at the centres `means` [N, 3] seen from `center` [3] (a tensor on
// their device: a graph's static input), and every Linear's input for the backward.
std::vector<Tensor> illumination_forward(Tensor means, Tensor center, std::vector<int> illum, double bound,
                                         Tensor weights) {
    const rgs::IllumConfig cfg = train_illum_config(illum);
    check_illum_inputs(means, center, cfg, bound, weights);
    means = means.contiguous(), center = center.contiguous();
    const int64_t N = means.size(0);
    const int64_t ld = illum_columns(N);
    Tensor rgb = torch::empty({N, 3}, means.options());
    Tensor A = torch::empty({rgs::illum_train_layout(cfg).a_width, ld}, means.options());
    A.narrow(1, N, ld - N).zero_();  // the padding adds nothing to the weight gradients
    RGS_DEVICE_GUARD(means);
    AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "illumination_forward", [&] {
        if (means.is_cuda()) {
#ifdef RGS_WITH_CUDA
            rgs::illumination_forward_cuda<scalar_t>(N, means.data_ptr<scalar_t>(), center.data_ptr<scalar_t>(), cfg,
                                                     bound, weights.data_ptr<scalar_t>(), rgb.data_ptr<scalar_t>(),
                                                     A.data_ptr<scalar_t>(), ld, RGS_CUDA_STREAM(means));
#else
            no_cuda();
#endif
        } else {
            rgs::illumination_forward_cpu<scalar_t>(N, means.data_ptr<scalar_t>(), center.data_ptr<scalar_t>(), cfg,
                                                    bound, weights.data_ptr<scalar_t>(), rgb.data_ptr<scalar_t>(),
                                                    A.data_ptr<scalar_t>(), ld, num_threads());
        }
    });
    return {rgb, A};
}

// (g_means [N, 3], D [d_width, illum_columns(N)]): the backward of illumination_forward given the gradient g_rgb [N, 3].
std::vector<Tensor> illumination_backward(Tensor means, Tensor center, std::vector<int> illum, double bound,
                                          Tensor weights, Tensor A, Tensor rgb, Tensor g_rgb) {
    const rgs::IllumConfig cfg = train_illum_config(illum);
    check_illum_inputs(means, center, cfg, bound, weights);
    const int64_t N = means.size(0);
    const rgs::IllumTrainLayout S = rgs::illum_train_layout(cfg);
    const int64_t ld = illum_columns(N);
    check_tensor(A, "A", {S.a_width, ld}, means);
    check_tensor(rgb, "rgb", {N, 3}, means);
    check_tensor(g_rgb, "g_rgb", {N, 3}, means);
    means = means.contiguous(), center = center.contiguous(), A = A.contiguous(), rgb = rgb.contiguous();
    g_rgb = g_rgb.contiguous();
    Tensor g_means = torch::empty({N, 3}, means.options());
    Tensor D = torch::empty({S.d_width, ld}, means.options());
    D.narrow(1, N, ld - N).zero_();
    RGS_DEVICE_GUARD(means);
    AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "illumination_backward", [&] {
        if (means.is_cuda()) {
#ifdef RGS_WITH_CUDA
            rgs::illumination_backward_cuda<scalar_t>(
                N, means.data_ptr<scalar_t>(), center.data_ptr<scalar_t>(), cfg, bound, weights.data_ptr<scalar_t>(),
                A.data_ptr<scalar_t>(), rgb.data_ptr<scalar_t>(), g_rgb.data_ptr<scalar_t>(), D.data_ptr<scalar_t>(),
                g_means.data_ptr<scalar_t>(), ld, RGS_CUDA_STREAM(means));
#else
            no_cuda();
#endif
        } else {
            rgs::illumination_backward_cpu<scalar_t>(
                N, means.data_ptr<scalar_t>(), center.data_ptr<scalar_t>(), cfg, bound, weights.data_ptr<scalar_t>(),
                A.data_ptr<scalar_t>(), rgb.data_ptr<scalar_t>(), g_rgb.data_ptr<scalar_t>(), D.data_ptr<scalar_t>(),
                g_means.data_ptr<scalar_t>(), ld, num_threads());
        }
    });
    return {g_means, D};
}

// [H, W, 3] srgb(s(gain · lin(R̂ ∘ L̂))) of a rendered [H, W, C >= 6] image (R̂ in channels 0-2, L̂ in 3-5), a
// gain [1] or [3] on the image's device and the highlight shoulder's knee s (>= 1: none): the exposure tone of
// retinexgs/model/tone.py, forward only.
Tensor exposure_tone(Tensor image, Tensor gain, double shoulder) {
    check_float(image, "image");
    RGS_CHECK_VALUE(image.dim() == 3 && image.size(2) >= 6, "image must be [H, W, C >= 6] (R̂, L̂), got shape ",
                    image.sizes());
    check_tensor(gain, "gain", {-1}, image);
    RGS_CHECK_VALUE(gain.size(0) == 1 || gain.size(0) == 3 || gain.size(0) == 9,
                    "gain must have 1 or 3 entries (or 9: a 3x3 matrix, row-major), got ", gain.size(0));
    RGS_CHECK_VALUE(shoulder > 0, "shoulder (the highlight knee) must be > 0, got ", shoulder);
    image = image.contiguous(), gain = gain.contiguous();
    const int64_t P = image.size(0) * image.size(1);
    const int C = int(image.size(2)), G = int(gain.size(0));
    Tensor out = torch::empty({image.size(0), image.size(1), 3}, image.options());
    RGS_DEVICE_GUARD(image);
    AT_DISPATCH_FLOATING_TYPES(image.scalar_type(), "exposure_tone", [&] {
        if (image.is_cuda()) {
#ifdef RGS_WITH_CUDA
            rgs::exposure_tone_cuda<scalar_t>(P, C, G, image.data_ptr<scalar_t>(), gain.data_ptr<scalar_t>(),
                                              shoulder, out.data_ptr<scalar_t>(), RGS_CUDA_STREAM(image));
#else
            no_cuda();
#endif
        } else {
            rgs::exposure_tone_cpu<scalar_t>(P, C, G, image.data_ptr<scalar_t>(), gain.data_ptr<scalar_t>(),
                                             shoulder, out.data_ptr<scalar_t>(), num_threads());
        }
    });
    return out;
}

// Adam's step (rgs/adam.h) over every given parameter tensor at once: param, exp_avg and exp_avg_sq updated in
// place; per tensor its group's beta1, beta2, eps and the step's step_size = lr / (1 - beta1^t), bc2_sqrt =
// sqrt(1 - beta2^t). One dtype and one device for all; each tensor contiguous and of its parameter's size.
void adam_step(std::vector<Tensor> params, std::vector<Tensor> grads, std::vector<Tensor> exp_avgs,
               std::vector<Tensor> exp_avg_sqs, std::vector<double> beta1, std::vector<double> beta2,
               std::vector<double> eps, std::vector<double> step_size, std::vector<double> bc2_sqrt) {
    const size_t n = params.size();
    RGS_CHECK_VALUE(grads.size() == n && exp_avgs.size() == n && exp_avg_sqs.size() == n && beta1.size() == n &&
                        beta2.size() == n && eps.size() == n && step_size.size() == n && bc2_sqrt.size() == n,
                    "adam_step needs one grad, exp_avg, exp_avg_sq, beta1, beta2, eps, step_size and bc2_sqrt per "
                    "param (", n, " params)");
    if (n == 0) return;
    const Tensor& first = params[0];
    RGS_CHECK_TYPE(first.scalar_type() == torch::kFloat32 || first.scalar_type() == torch::kFloat64,
                   "adam_step needs float32 or float64 tensors, got ", first.scalar_type());
    for (size_t k = 0; k < n; ++k) {
        for (const Tensor* t : {&params[k], &grads[k], &exp_avgs[k], &exp_avg_sqs[k]}) {
            RGS_CHECK_TYPE(t->scalar_type() == first.scalar_type(), "adam_step: tensor ", k, " has dtype ",
                           t->scalar_type(), ", the first param ", first.scalar_type());
            RGS_CHECK_VALUE(t->device() == first.device(), "adam_step: tensor ", k, " is on ", t->device(),
                            ", the first param on ", first.device());
            RGS_CHECK_VALUE(t->is_contiguous(), "adam_step: tensor ", k, " is not contiguous");
            RGS_CHECK_VALUE(t->numel() == params[k].numel(), "adam_step: tensor ", k, " has ", t->numel(),
                            " elements, its param ", params[k].numel());
        }
        RGS_CHECK_VALUE(bc2_sqrt[k] > 0.0, "adam_step: bc2_sqrt must be > 0, got ", bc2_sqrt[k]);
    }
    RGS_DEVICE_GUARD(first);
    AT_DISPATCH_FLOATING_TYPES(first.scalar_type(), "adam_step", [&] {
        std::vector<rgs::AdamTensor<scalar_t>> list(n);
        for (size_t k = 0; k < n; ++k)
            list[k] = rgs::AdamTensor<scalar_t>{params[k].data_ptr<scalar_t>(), grads[k].data_ptr<scalar_t>(),
                                                exp_avgs[k].data_ptr<scalar_t>(), exp_avg_sqs[k].data_ptr<scalar_t>(),
                                                params[k].numel(), scalar_t(beta1[k]), scalar_t(beta2[k]),
                                                scalar_t(1.0 - beta1[k]), scalar_t(1.0 - beta2[k]),
                                                scalar_t(eps[k]), scalar_t(step_size[k]), scalar_t(bc2_sqrt[k])};
        if (first.is_cuda()) {
#ifdef RGS_WITH_CUDA
            rgs::adam_step_cuda<scalar_t>(list.data(), int(n), RGS_CUDA_STREAM(first));
#else
            no_cuda();
#endif
        } else {
            rgs::adam_step_cpu<scalar_t>(list.data(), int(n), num_threads());
        }
    });
}

// Training's tone curve (rgs/tone_curve.h): y = srgb_o(s(gain · lin_i(x))) elementwise over a contiguous x of any
// shape, gain [C] on x's device, element i taking gain[(i / inner) % C]; knee the shoulder's (>= 1: none); forms
// rgs::CurveForm (0 clip, 1 open, 2 extended; the output's also 3: linear). The backward returns grad_x and the
// per-element gain gradient, each only where asked (an empty tensor otherwise); the caller sums the latter per
// channel.
static void check_tone_curve(const Tensor& x, const Tensor& gain, int64_t C, int64_t inner, int form_in,
                             int form_out) {
    check_float(x, "x");
    check_tensor(gain, "gain", {C}, x);
    RGS_CHECK_VALUE(C >= 1 && inner >= 1, "tone_curve needs C >= 1 and inner >= 1, got ", C, " and ", inner);
    RGS_CHECK_VALUE(C == 1 || x.numel() % (C * inner) == 0, "x's ", x.numel(),
                    " elements are not a multiple of C * inner = ", C * inner);
    RGS_CHECK_VALUE(form_in >= 0 && form_in <= 2 && form_out >= 0 && form_out <= 3,
                    "tone_curve forms must be 0 (clip), 1 (open) or 2 (extended), the output's also 3 (linear), got ",
                    form_in, " and ", form_out);
}

Tensor tone_curve_forward(Tensor x, Tensor gain, int64_t C, int64_t inner, double knee, int form_in, int form_out) {
    check_tone_curve(x, gain, C, inner, form_in, form_out);
    x = x.contiguous(), gain = gain.contiguous();
    Tensor y = torch::empty_like(x);
    const int64_t n = x.numel();
    RGS_DEVICE_GUARD(x);
    AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "tone_curve_forward", [&] {
        if (x.is_cuda()) {
#ifdef RGS_WITH_CUDA
            rgs::tone_curve_forward_cuda<scalar_t>(n, x.data_ptr<scalar_t>(), gain.data_ptr<scalar_t>(), C, inner, knee,
                                                   form_in, form_out, y.data_ptr<scalar_t>(), RGS_CUDA_STREAM(x));
#else
            no_cuda();
#endif
        } else {
            rgs::tone_curve_forward_cpu<scalar_t>(n, x.data_ptr<scalar_t>(), gain.data_ptr<scalar_t>(), C, inner, knee,
                                                  form_in, form_out, y.data_ptr<scalar_t>(), num_threads());
        }
    });
    return y;
}

std::tuple<Tensor, Tensor> tone_curve_backward(Tensor x, Tensor gain, Tensor grad_out, int64_t C, int64_t inner,
                                               double knee, int form_in, int form_out, bool need_x, bool need_gain) {
    check_tone_curve(x, gain, C, inner, form_in, form_out);
    check_tensor(grad_out, "grad_out", std::vector<int64_t>(x.sizes().begin(), x.sizes().end()), x);
    x = x.contiguous(), gain = gain.contiguous(), grad_out = grad_out.contiguous();
    Tensor grad_x = need_x ? torch::empty_like(x) : torch::empty({0}, x.options());
    Tensor grad_k = need_gain ? torch::empty_like(x) : torch::empty({0}, x.options());
    const int64_t n = x.numel();
    RGS_DEVICE_GUARD(x);
    AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "tone_curve_backward", [&] {
        scalar_t* gx = need_x ? grad_x.data_ptr<scalar_t>() : nullptr;
        scalar_t* gk = need_gain ? grad_k.data_ptr<scalar_t>() : nullptr;
        if (x.is_cuda()) {
#ifdef RGS_WITH_CUDA
            rgs::tone_curve_backward_cuda<scalar_t>(n, x.data_ptr<scalar_t>(), gain.data_ptr<scalar_t>(), C, inner,
                                                    knee, form_in, form_out, grad_out.data_ptr<scalar_t>(), gx, gk,
                                                    RGS_CUDA_STREAM(x));
#else
            no_cuda();
#endif
        } else {
            rgs::tone_curve_backward_cpu<scalar_t>(n, x.data_ptr<scalar_t>(), gain.data_ptr<scalar_t>(), C, inner,
                                                   knee, form_in, form_out, grad_out.data_ptr<scalar_t>(), gx, gk,
                                                   num_threads());
        }
    });
    return {grad_x, grad_k};
}

// L_enhance of the default configuration with its gradient in the gain (rgs/enhance_loss.h): x = R̂∘L̂ and s [H, W, 3]
// (H, W >= pool), gain [3], E [1], one float dtype and device. Returns [12]: (spa, exp, col), then d(term)/d(gain_c)
// term by term.
Tensor enhance_loss(Tensor x, Tensor s, Tensor gain, Tensor E, int64_t pool, double knee, int form_in, int form_out,
                    bool exp_l1, bool scale_invariant) {
    check_float(x, "x");
    RGS_CHECK_VALUE(x.dim() == 3 && x.size(2) == 3, "x must have shape (H, W, 3), got ", x.sizes());
    const int64_t H = x.size(0), W = x.size(1);
    check_tensor(s, "s", {H, W, 3}, x);
    check_tensor(gain, "gain", {3}, x);
    check_tensor(E, "E", {1}, x);
    RGS_CHECK_VALUE(pool >= 1 && H >= pool && W >= pool, "enhance_loss needs 1 <= pool <= H, W, got pool ", pool,
                    " for ", H, "x", W);
    RGS_CHECK_VALUE(form_in >= 0 && form_in <= 2 && form_out >= 0 && form_out <= 3,
                    "enhance_loss forms must be 0 (clip), 1 (open) or 2 (extended), the output's also 3 (linear), got ",
                    form_in, " and ", form_out);
    x = x.contiguous(), s = s.contiguous(), gain = gain.contiguous(), E = E.contiguous();
    const int64_t cells_n = ((H + pool - 1) / pool) * ((W + pool - 1) / pool);
    Tensor cells = torch::empty({cells_n, rgs::kEnhanceCellValues}, x.options());
    Tensor out = torch::empty({rgs::kEnhanceOut}, x.options());
    RGS_DEVICE_GUARD(x);
    AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "enhance_loss", [&] {
        if (x.is_cuda()) {
#ifdef RGS_WITH_CUDA
            Tensor scratch = torch::empty({rgs::enhance_scratch_cuda(H, W, int(pool))},
                                          x.options().dtype(torch::kFloat64));
            rgs::enhance_loss_cuda<scalar_t>(x.data_ptr<scalar_t>(), s.data_ptr<scalar_t>(), H, W, int(pool),
                                             gain.data_ptr<scalar_t>(), knee, form_in, form_out, E.data_ptr<scalar_t>(),
                                             exp_l1, scale_invariant, cells.data_ptr<scalar_t>(),
                                             scratch.data_ptr<double>(), out.data_ptr<scalar_t>(), RGS_CUDA_STREAM(x));
#else
            no_cuda();
#endif
        } else {
            rgs::enhance_loss_cpu<scalar_t>(x.data_ptr<scalar_t>(), s.data_ptr<scalar_t>(), H, W, int(pool),
                                            gain.data_ptr<scalar_t>(), knee, form_in, form_out, E.data_ptr<scalar_t>(),
                                            exp_l1, scale_invariant, cells.data_ptr<scalar_t>(),
                                            out.data_ptr<scalar_t>(), num_threads());
        }
    });
    return out;
}

// The training loss's supervision, L_TV and depth prior in one pass each way (rgs/supervision.h). image [H, W, 6|8],
// packed [H, W, 7|9] (8 and 9 together: the depth prior), one float dtype and device; the gains [1], noise a, b [3]
// and confidence [H, W] optional, on that device. Returns (x9, y9 [9, H, W], partials [rows, kSums]).
struct SupervisionInputs {
    Tensor image, packed;
    std::optional<Tensor> ssim_gain, lin_gain, noise_a, noise_b, conf;
};

template <typename T>
rgs::SupervisionArgs<T> supervision_args(const SupervisionInputs& in, int rec_form, int s_form, double relative_eps,
                                         double min_alpha, double depth_eps, double r_luma) {
    auto ptr = [](const std::optional<Tensor>& t) { return t ? t->data_ptr<T>() : (const T*)nullptr; };
    rgs::SupervisionArgs<T> a;
    a.H = int(in.image.size(0)), a.W = int(in.image.size(1));
    a.ci = int(in.image.size(2)), a.k = int(in.packed.size(2));
    a.rec_form = rec_form, a.s_form = s_form;
    a.ssim_gain = ptr(in.ssim_gain), a.lin_gain = ptr(in.lin_gain);
    a.noise_a = ptr(in.noise_a), a.noise_b = ptr(in.noise_b), a.conf = ptr(in.conf);
    a.relative_eps = T(relative_eps), a.min_alpha = T(min_alpha), a.depth_eps = T(depth_eps);
    a.r_luma = T(r_luma);
    return a;
}

static SupervisionInputs check_supervision(Tensor image, Tensor packed, std::optional<Tensor> ssim_gain,
                                           std::optional<Tensor> lin_gain, std::optional<Tensor> noise_a,
                                           std::optional<Tensor> noise_b, std::optional<Tensor> conf, int rec_form,
                                           int s_form) {
    check_float(image, "image");
    RGS_CHECK_VALUE(image.dim() == 3 && (image.size(2) == 6 || image.size(2) == 8),
                    "image must be [H, W, 6] or [H, W, 8], got shape ", image.sizes());
    const int64_t H = image.size(0), W = image.size(1);
    const int64_t k = image.size(2) == 8 ? 9 : 7;
    check_tensor(packed, "packed", {H, W, k}, image);
    RGS_CHECK_VALUE(rec_form >= rgs::kRecPlain && rec_form <= rgs::kRecRelative, "rec_form must be 0-3, got ", rec_form);
    RGS_CHECK_VALUE(s_form == rgs::kOpen || s_form == rgs::kExtended, "s_form must be 1 (open) or 2 (extended), got ",
                    s_form);
    RGS_CHECK_VALUE(rec_form == rgs::kRecPlain || lin_gain, "rec_form ", rec_form, " needs lin_gain");
    RGS_CHECK_VALUE(rec_form != rgs::kRecNoise || (noise_a && noise_b), "rec_form 2 (noise) needs noise_a and noise_b");
    SupervisionInputs in{image.contiguous(), packed.contiguous(), ssim_gain, lin_gain, noise_a, noise_b, conf};
    for (auto [t, name, n] : {std::tuple<std::optional<Tensor>*, const char*, int64_t>{&in.ssim_gain, "ssim_gain", 1},
                              {&in.lin_gain, "lin_gain", 1}, {&in.noise_a, "noise_a", 3}, {&in.noise_b, "noise_b", 3}}) {
        if (*t) {
            check_tensor(**t, name, {n}, image);
            *t = (*t)->contiguous();
        }
    }
    if (in.conf) {
        check_tensor(*in.conf, "conf", {H, W}, image);
        in.conf = in.conf->contiguous();
    }
    return in;
}

std::tuple<Tensor, Tensor, Tensor> supervision_forward(Tensor image, Tensor packed, std::optional<Tensor> ssim_gain,
                                                       std::optional<Tensor> lin_gain, std::optional<Tensor> noise_a,
                                                       std::optional<Tensor> noise_b, std::optional<Tensor> conf,
                                                       int rec_form, int s_form, double relative_eps, double min_alpha,
                                                       double depth_eps, double r_luma) {
    const auto in = check_supervision(image, packed, ssim_gain, lin_gain, noise_a, noise_b, conf, rec_form, s_form);
    RGS_CHECK_VALUE(r_luma >= 0.0 && r_luma <= 1.0, "r_luma must be in [0, 1], got ", r_luma);
    const int64_t H = image.size(0), W = image.size(1);
    Tensor x9 = torch::empty({9, H, W}, image.options());
    Tensor y9 = torch::empty({9, H, W}, image.options());
    Tensor partials;
    RGS_DEVICE_GUARD(image);
    AT_DISPATCH_FLOATING_TYPES(image.scalar_type(), "supervision_forward", [&] {
        const auto a = supervision_args<scalar_t>(in, rec_form, s_form, relative_eps, min_alpha, depth_eps, r_luma);
        if (image.is_cuda()) {
#ifdef RGS_WITH_CUDA
            partials = torch::empty({rgs::supervision_rows_cuda(H * W), int64_t(rgs::kSums)}, image.options());
            rgs::supervision_forward_cuda<scalar_t>(a, in.image.data_ptr<scalar_t>(), in.packed.data_ptr<scalar_t>(),
                                                    x9.data_ptr<scalar_t>(), y9.data_ptr<scalar_t>(),
                                                    partials.data_ptr<scalar_t>(), RGS_CUDA_STREAM(image));
#else
            no_cuda();
#endif
        } else {
            const int rows = int(std::max<int64_t>(1, std::min<int64_t>(H * W / 4096, 256)));
            partials = torch::empty({rows, int64_t(rgs::kSums)}, image.options());
            rgs::supervision_forward_cpu<scalar_t>(a, in.image.data_ptr<scalar_t>(), in.packed.data_ptr<scalar_t>(),
                                                   x9.data_ptr<scalar_t>(), y9.data_ptr<scalar_t>(),
                                                   partials.data_ptr<scalar_t>(), rows, num_threads());
        }
    });
    return {x9, y9, partials};
}

Tensor supervision_backward(Tensor image, Tensor packed, std::optional<Tensor> ssim_gain, std::optional<Tensor> lin_gain,
                            std::optional<Tensor> noise_a, std::optional<Tensor> noise_b, std::optional<Tensor> conf,
                            std::optional<Tensor> g_x9, Tensor g_sums, int rec_form, int s_form, double relative_eps,
                            double min_alpha, double depth_eps, double r_luma) {
    const auto in = check_supervision(image, packed, ssim_gain, lin_gain, noise_a, noise_b, conf, rec_form, s_form);
    RGS_CHECK_VALUE(r_luma >= 0.0 && r_luma <= 1.0, "r_luma must be in [0, 1], got ", r_luma);
    const int64_t H = image.size(0), W = image.size(1);
    check_tensor(g_sums, "g_sums", {int64_t(rgs::kSums)}, image);
    g_sums = g_sums.contiguous();
    if (g_x9) {
        check_tensor(*g_x9, "g_x9", {9, H, W}, image);
        g_x9 = g_x9->contiguous();
    }
    Tensor grad = torch::empty_like(in.image);
    RGS_DEVICE_GUARD(image);
    AT_DISPATCH_FLOATING_TYPES(image.scalar_type(), "supervision_backward", [&] {
        const auto a = supervision_args<scalar_t>(in, rec_form, s_form, relative_eps, min_alpha, depth_eps, r_luma);
        const scalar_t* gx = g_x9 ? g_x9->data_ptr<scalar_t>() : nullptr;
        if (image.is_cuda()) {
#ifdef RGS_WITH_CUDA
            rgs::supervision_backward_cuda<scalar_t>(a, in.image.data_ptr<scalar_t>(), in.packed.data_ptr<scalar_t>(),
                                                     gx, g_sums.data_ptr<scalar_t>(), grad.data_ptr<scalar_t>(),
                                                     RGS_CUDA_STREAM(image));
#else
            no_cuda();
#endif
        } else {
            rgs::supervision_backward_cpu<scalar_t>(a, in.image.data_ptr<scalar_t>(), in.packed.data_ptr<scalar_t>(), gx,
                                                    g_sums.data_ptr<scalar_t>(), grad.data_ptr<scalar_t>(),
                                                    num_threads());
        }
    });
    return grad;
}

// Densification's screen-space statistics of one view, added in place (rgs/screen_stats.h): grad2d [N, 2] the
// projected centres' pixel gradients (float32/64), radii [N, 2] int32, (sx, sy) = (W / 2, H / 2); grad_accum,
// count, max_radius: [N] float32, contiguous, on grad2d's device.
void screen_stats(Tensor grad2d, Tensor radii, double sx, double sy, Tensor grad_accum, Tensor count,
                  Tensor max_radius) {
    check_float(grad2d, "grad2d");
    RGS_CHECK_VALUE(grad2d.dim() == 2 && grad2d.size(1) == 2, "grad2d must be [N, 2], got shape ", grad2d.sizes());
    const int64_t N = grad2d.size(0);
    check_index(radii, "radii", {N, 2}, grad2d);
    for (const auto& [t, name] : {std::pair<const Tensor&, const char*>{grad_accum, "grad_accum"},
                                  {count, "count"}, {max_radius, "max_radius"}}) {
        RGS_CHECK_TYPE(t.scalar_type() == torch::kFloat32, name, " must be float32, got ", t.scalar_type());
        RGS_CHECK_VALUE(t.device() == grad2d.device(), name, " must be on ", grad2d.device(), ", got ", t.device());
        RGS_CHECK_VALUE(t.dim() == 1 && t.size(0) == N, name, " must be [", N, "], got shape ", t.sizes());
        RGS_CHECK_VALUE(t.is_contiguous(), name, " must be contiguous (it is updated in place)");
    }
    grad2d = grad2d.contiguous(), radii = radii.contiguous();
    RGS_DEVICE_GUARD(grad2d);
    AT_DISPATCH_FLOATING_TYPES(grad2d.scalar_type(), "screen_stats", [&] {
        if (grad2d.is_cuda()) {
#ifdef RGS_WITH_CUDA
            rgs::screen_stats_cuda<scalar_t>(N, grad2d.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(), sx, sy,
                                             grad_accum.data_ptr<float>(), count.data_ptr<float>(),
                                             max_radius.data_ptr<float>(), RGS_CUDA_STREAM(grad2d));
#else
            no_cuda();
#endif
        } else {
            rgs::screen_stats_cpu<scalar_t>(N, grad2d.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(), sx, sy,
                                            grad_accum.data_ptr<float>(), count.data_ptr<float>(),
                                            max_radius.data_ptr<float>(), num_threads());
        }
    });
}

// The training loss's fused SSIM (rgs/ssim.h). x, y: [..., H, W] of one dtype and device (every leading index a
// plane); window: the 1-D taps (odd count <= 15, any dtype, read on the host). Returns (S map, partials [3, ...] or
// an empty tensor when partials is false).
template <typename T>
rgs::SsimWindow<T> ssim_window(const Tensor& window, double c1, double c2) {
    RGS_CHECK_VALUE(window.dim() == 1 && window.size(0) % 2 == 1 && window.size(0) <= 2 * rgs::kSsimMaxRadius + 1,
                    "window must be 1-D with an odd number of taps <= ", 2 * rgs::kSsimMaxRadius + 1, ", got shape ",
                    window.sizes());
    Tensor taps = window.detach().to(torch::kCPU, torch::kFloat64).contiguous();
    rgs::SsimWindow<T> win{};
    win.radius = int(taps.size(0) / 2);
    for (int64_t i = 0; i < taps.size(0); ++i) win.w[i] = T(taps.data_ptr<double>()[i]);
    win.c1 = T(c1), win.c2 = T(c2);
    return win;
}

void check_ssim_images(const Tensor& x, const Tensor& y) {
    check_float(x, "x");
    RGS_CHECK_VALUE(x.dim() >= 2, "x must be [..., H, W], got shape ", x.sizes());
    RGS_CHECK_VALUE(y.sizes() == x.sizes(), "y has shape ", y.sizes(), ", x has ", x.sizes());
    RGS_CHECK_TYPE(y.scalar_type() == x.scalar_type(), "y must have dtype ", x.scalar_type(), ", got ",
                   y.scalar_type());
    RGS_CHECK_VALUE(y.device() == x.device(), "y must be on ", x.device(), ", got ", y.device());
}

std::tuple<Tensor, Tensor> ssim_forward(Tensor x, Tensor y, Tensor window, double c1, double c2, bool partials) {
    check_ssim_images(x, y);
    x = x.contiguous(), y = y.contiguous();
    const int H = int(x.size(-2)), W = int(x.size(-1));
    const int64_t planes = H * int64_t(W) == 0 ? 0 : x.numel() / (H * int64_t(W));
    Tensor s = torch::empty_like(x);
    std::vector<int64_t> dshape{3};
    for (int64_t v : x.sizes()) dshape.push_back(v);
    Tensor d = partials ? torch::empty(dshape, x.options()) : torch::empty({0}, x.options());
    RGS_DEVICE_GUARD(x);
    AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "ssim_forward", [&] {
        const auto win = ssim_window<scalar_t>(window, c1, c2);
        scalar_t* dp = partials ? d.data_ptr<scalar_t>() : nullptr;
        if (x.is_cuda()) {
#ifdef RGS_WITH_CUDA
            rgs::ssim_forward_cuda<scalar_t>(planes, H, W, x.data_ptr<scalar_t>(), y.data_ptr<scalar_t>(), win,
                                             s.data_ptr<scalar_t>(), dp, RGS_CUDA_STREAM(x));
#else
            no_cuda();
#endif
        } else {
            rgs::ssim_forward_cpu<scalar_t>(planes, H, W, x.data_ptr<scalar_t>(), y.data_ptr<scalar_t>(), win,
                                            s.data_ptr<scalar_t>(), dp, num_threads());
        }
    });
    return {s, d};
}

Tensor ssim_backward(Tensor grad, Tensor x, Tensor y, Tensor partials, Tensor window) {
    check_ssim_images(x, y);
    check_ssim_images(grad, x);
    RGS_CHECK_VALUE(partials.dim() == x.dim() + 1 && partials.size(0) == 3 && partials.numel() == 3 * x.numel(),
                    "partials must be [3, ...] of x's shape, got shape ", partials.sizes());
    RGS_CHECK_TYPE(partials.scalar_type() == x.scalar_type(), "partials must have dtype ", x.scalar_type());
    RGS_CHECK_VALUE(partials.device() == x.device(), "partials must be on ", x.device());
    grad = grad.contiguous(), x = x.contiguous(), y = y.contiguous(), partials = partials.contiguous();
    const int H = int(x.size(-2)), W = int(x.size(-1));
    const int64_t planes = H * int64_t(W) == 0 ? 0 : x.numel() / (H * int64_t(W));
    Tensor dx = torch::empty_like(x);
    RGS_DEVICE_GUARD(x);
    AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "ssim_backward", [&] {
        const auto win = ssim_window<scalar_t>(window, 0.0, 0.0);
        if (x.is_cuda()) {
#ifdef RGS_WITH_CUDA
            rgs::ssim_backward_cuda<scalar_t>(planes, H, W, grad.data_ptr<scalar_t>(), x.data_ptr<scalar_t>(),
                                              y.data_ptr<scalar_t>(), partials.data_ptr<scalar_t>(), win,
                                              dx.data_ptr<scalar_t>(), RGS_CUDA_STREAM(x));
#else
            no_cuda();
#endif
        } else {
            rgs::ssim_backward_cpu<scalar_t>(planes, H, W, grad.data_ptr<scalar_t>(), x.data_ptr<scalar_t>(),
                                             y.data_ptr<scalar_t>(), partials.data_ptr<scalar_t>(), win,
                                             dx.data_ptr<scalar_t>(), num_threads());
        }
    });
    return dx;
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
    m.doc() = "RetinexGS kernel library: projection, tile binning, compositing and SH (CPU/OpenMP and CUDA)";
    m.def("project_forward", &project_forward, pybind11::arg("means"), pybind11::arg("quats"), pybind11::arg("scales"),
          pybind11::arg("opacities"), pybind11::arg("viewmat"), pybind11::arg("fx"), pybind11::arg("fy"),
          pybind11::arg("cx"), pybind11::arg("cy"), pybind11::arg("width"), pybind11::arg("height"),
          pybind11::arg("near_plane"), pybind11::arg("far_plane"), pybind11::arg("check_finite") = false,
          pybind11::arg("colors") = pybind11::none(), pybind11::arg("background") = pybind11::none());
    m.def("project_backward", &project_backward);
    m.def("bin_gaussians", &bin_gaussians, pybind11::arg("means2d"), pybind11::arg("radii"), pybind11::arg("depths"),
          pybind11::arg("width"), pybind11::arg("height"), pybind11::arg("conics") = pybind11::none(),
          pybind11::arg("opacities") = pybind11::none(), pybind11::arg("capacity") = -1,
          pybind11::arg("count") = pybind11::none());
    m.def("rasterize_forward", &rasterize_forward, pybind11::arg("means2d"), pybind11::arg("conics"),
          pybind11::arg("colors"), pybind11::arg("opacities"), pybind11::arg("gauss_ids"),
          pybind11::arg("tile_ranges"), pybind11::arg("width"), pybind11::arg("height"),
          pybind11::arg("background") = pybind11::none(), pybind11::arg("alpha") = false);
    m.def("rasterize_backward", &rasterize_backward, pybind11::arg("means2d"), pybind11::arg("conics"),
          pybind11::arg("colors"), pybind11::arg("opacities"), pybind11::arg("gauss_ids"),
          pybind11::arg("tile_ranges"), pybind11::arg("width"), pybind11::arg("height"),
          pybind11::arg("transmittance"), pybind11::arg("last_ids"), pybind11::arg("v_image"),
          pybind11::arg("v_transmittance") = pybind11::none(), pybind11::arg("background") = pybind11::none(),
          pybind11::arg("alpha") = false);
    m.def("sh_forward", &sh_forward);
    m.def("sh_backward", &sh_backward);
    m.def("pack_illum_weights", &pack_illum_weights);
    m.def("gaussian_colors", &gaussian_colors, pybind11::arg("degree"), pybind11::arg("means"),
          pybind11::arg("sh_dc"), pybind11::arg("sh_rest"), pybind11::arg("center"), pybind11::arg("illum") = pybind11::none(),
          pybind11::arg("bound") = 1.0, pybind11::arg("weights") = pybind11::none());
    m.def("illumination_train_layout", &illumination_train_layout, pybind11::arg("illum"));
    m.def("illumination_forward", &illumination_forward, pybind11::arg("means"), pybind11::arg("center"),
          pybind11::arg("illum"), pybind11::arg("bound"), pybind11::arg("weights"));
    m.def("illumination_backward", &illumination_backward, pybind11::arg("means"), pybind11::arg("center"),
          pybind11::arg("illum"), pybind11::arg("bound"), pybind11::arg("weights"), pybind11::arg("A"),
          pybind11::arg("rgb"), pybind11::arg("g_rgb"));
    m.def("exposure_tone", &exposure_tone, pybind11::arg("image"), pybind11::arg("gain"),
          pybind11::arg("shoulder") = 1.0);
    m.def("tone_curve_forward", &tone_curve_forward, pybind11::arg("x"), pybind11::arg("gain"), pybind11::arg("C"),
          pybind11::arg("inner"), pybind11::arg("knee"), pybind11::arg("form_in"), pybind11::arg("form_out"));
    m.def("tone_curve_backward", &tone_curve_backward, pybind11::arg("x"), pybind11::arg("gain"),
          pybind11::arg("grad_out"), pybind11::arg("C"), pybind11::arg("inner"), pybind11::arg("knee"),
          pybind11::arg("form_in"), pybind11::arg("form_out"), pybind11::arg("need_x"), pybind11::arg("need_gain"));
    m.def("enhance_loss", &enhance_loss, pybind11::arg("x"), pybind11::arg("s"), pybind11::arg("gain"),
          pybind11::arg("E"), pybind11::arg("pool"), pybind11::arg("knee"), pybind11::arg("form_in"),
          pybind11::arg("form_out"), pybind11::arg("exp_l1"), pybind11::arg("scale_invariant"));
    m.def("adam_step", &adam_step, pybind11::arg("params"), pybind11::arg("grads"), pybind11::arg("exp_avgs"),
          pybind11::arg("exp_avg_sqs"), pybind11::arg("beta1"), pybind11::arg("beta2"), pybind11::arg("eps"),
          pybind11::arg("step_size"), pybind11::arg("bc2_sqrt"));
    m.def("screen_stats", &screen_stats, pybind11::arg("grad2d"), pybind11::arg("radii"), pybind11::arg("sx"),
          pybind11::arg("sy"), pybind11::arg("grad_accum"), pybind11::arg("count"), pybind11::arg("max_radius"));
    m.def("ssim_forward", &ssim_forward, pybind11::arg("x"), pybind11::arg("y"), pybind11::arg("window"),
          pybind11::arg("c1"), pybind11::arg("c2"), pybind11::arg("partials"));
    m.def("ssim_backward", &ssim_backward, pybind11::arg("grad"), pybind11::arg("x"), pybind11::arg("y"),
          pybind11::arg("partials"), pybind11::arg("window"));
    m.def("supervision_forward", &supervision_forward, pybind11::arg("image"), pybind11::arg("packed"),
          pybind11::arg("ssim_gain"), pybind11::arg("lin_gain"), pybind11::arg("noise_a"), pybind11::arg("noise_b"),
          pybind11::arg("conf"), pybind11::arg("rec_form"), pybind11::arg("s_form"), pybind11::arg("relative_eps"),
          pybind11::arg("min_alpha"), pybind11::arg("depth_eps"), pybind11::arg("r_luma"));
    m.def("supervision_backward", &supervision_backward, pybind11::arg("image"), pybind11::arg("packed"),
          pybind11::arg("ssim_gain"), pybind11::arg("lin_gain"), pybind11::arg("noise_a"), pybind11::arg("noise_b"),
          pybind11::arg("conf"), pybind11::arg("g_x9"), pybind11::arg("g_sums"), pybind11::arg("rec_form"),
          pybind11::arg("s_form"), pybind11::arg("relative_eps"), pybind11::arg("min_alpha"),
          pybind11::arg("depth_eps"), pybind11::arg("r_luma"));
    m.attr("max_illum_width") = rgs::kMaxIllumWidth;
    m.attr("illum_chunk") = kIllumChunk;
    m.attr("max_illum_freqs") = rgs::kMaxIllumFreqs;
    m.def("set_num_threads", [](int n) { g_num_threads = n; },
          "OpenMP threads for the CPU kernels (0: torch.get_num_threads())");
    m.def("get_num_threads", &num_threads);
#ifdef RGS_WITH_CUDA
    m.attr("has_cuda") = true;
#else
    m.attr("has_cuda") = false;
#endif
    m.attr("tile_size") = rgs::kTileSize;
}
