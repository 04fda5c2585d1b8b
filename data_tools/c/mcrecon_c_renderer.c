/* mcrecon_c_renderer.c - a minimal out-of-process renderer in C, written from
 * docs/renderer-protocol.md with the HDF5 C API only.
 *
 *   mcrecon adapt --renderer-cmd "data_tools/c/mcrecon_c_renderer {request} {reply}" \
 *       --size 64x64 --spp 16 --method gem -o out.exr --log run.h5
 *
 * It reads the request file (root attributes width, height, round, seed, n_total,
 * channels; datasets /counts and/or /positions, and /first_index), renders a procedural image (a
 * bright disc over a gradient, times a per-sample noise factor) and
 * writes the reply, a sample log: /positions (N, 2) float64, /values (N, C)
 * float32 and the three canonical per-sample features of the surface each
 * sample sees (docs/renderer-protocol.md, "Per-sample features"):
 * /features/albedo (N, 3), /features/normal (N, 3) and /features/depth (N,),
 * float32, which mcrecon keeps in the run's log and feature-guided methods
 * read.  The disc is a hemisphere bulging toward the camera (albedo
 * (0.8, 0.5, 0.2), its normal, depth 1 - its height); the gradient behind it
 * a plane (albedo 0.5 grey, normal +z, depth 1 + y / height).  The counted
 * samples come first, pixel by pixel, then one sample per requested position,
 * in request order.
 *
 * Sampling: every sample is a point of its pixel's own Owen-scrambled Sobol
 * sequence over its three dimensions (film x, film y, the noise), exactly the
 * sampler of mcrecon's built-in scenes (mcrecon/renderers/scenes/sobol.py,
 * sampler="sobol"; Burley 2020): padded 2-D Sobol pairs (dimensions 0-1, then
 * 2 with its unused partner), each pair at a hash-shuffled index, each
 * coordinate nested-uniform scrambled, every seed a hash of (scramble seed,
 * pixel, dimension).  The request's /first_index (optional; all zeros without
 * it) says where each pixel's sequence goes on: pixel p's counted samples take
 * the indices first_index[p], first_index[p] + 1, ..., then its requested
 * positions the indices after them (their x and y are given; the noise is
 * dimension 2 of that index).  The scramble seed is the renderer's own and the
 * same in every round (0; the request's seed changes every round and would
 * break the sequence): four rounds of 8 samples are sample for sample one
 * request of 32, and as stratified.  The reply says so (root attribute
 * sampler = "sobol", docs/renderer-protocol.md), so the adaptive methods hand
 * out each pixel's samples in whole nets.
 *
 * It reads string attributes of either HDF5 string type (variable-length UTF-8
 * as mcrecon writes them, or fixed-length ASCII) and integers of any width (HDF5
 * converts them to long long on read), and writes the reply's strings as
 * fixed-length ASCII, which mcrecon accepts as well.
 *
 * Build: make -C data_tools/c   (or: gcc -O2 -o mcrecon_c_renderer mcrecon_c_renderer.c
 *        $(pkg-config --cflags --libs hdf5) -lm;  or: h5cc -O2 -o mcrecon_c_renderer mcrecon_c_renderer.c -lm)
 */
#include <hdf5.h>
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const char *g_path = "request";

static void fail(const char *what) {
    fprintf(stderr, "mcrecon_c_renderer: %s: %s\n", g_path, what);
    exit(1);
}
#define CHECK(expr, what) do { if ((expr) < 0) fail(what " failed"); } while (0)

/* ---------------------------------------------------------------- the per-pixel scrambled Sobol sequence */
#define SCRAMBLE_SEED 0ull /* the renderer's own, fixed across rounds */
#define N_DIMS 3           /* film x, film y, noise */

static uint64_t reverse32(uint64_t x) {
    x &= 0xFFFFFFFFull;
    x = ((x >> 1) & 0x55555555ull) | ((x & 0x55555555ull) << 1);
    x = ((x >> 2) & 0x33333333ull) | ((x & 0x33333333ull) << 2);
    x = ((x >> 4) & 0x0F0F0F0Full) | ((x & 0x0F0F0F0Full) << 4);
    x = ((x >> 8) & 0x00FF00FFull) | ((x & 0x00FF00FFull) << 8);
    x = ((x >> 16) & 0x0000FFFFull) | ((x & 0x0000FFFFull) << 16);
    return x & 0xFFFFFFFFull;
}

/* Burley's Laine-Karras-style permutation of 32 bits: output bit j depends on input bits <= j only. */
static uint64_t laine_karras(uint64_t x, uint64_t seed) {
    const uint64_t m = 0xFFFFFFFFull;
    x = (x + seed) & m;
    x ^= (x * 0x6C50B47Cull) & m;
    x ^= (x * 0xB82F1E52ull) & m;
    x ^= (x * 0xC7AFE638ull) & m;
    x ^= (x * 0x8D22F6E6ull) & m;
    return x;
}

/* Owen scramble of a 32-bit fraction (bit j from the top flipped by a hash of the bits above it); applied
 * to an index, it maps every aligned block of 2^k indices onto an aligned block. */
static uint64_t nested_uniform_scramble(uint64_t x, uint64_t seed) { return reverse32(laine_karras(reverse32(x), seed)); }

/* The first two Sobol dimensions at index i (32-bit fractions): van der Corput and its Pascal partner. */
static void sobol2(uint64_t i, uint64_t *x, uint64_t *y) {
    uint64_t v = 0x80000000ull;
    *x = reverse32(i);
    *y = 0;
    for (uint64_t k = i; k; k >>= 1, v ^= v >> 1)
        if (k & 1) *y ^= v;
}

static uint64_t mix64(uint64_t z) { /* SplitMix64's finaliser */
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
}

static uint64_t hash_seed(uint64_t pixel, uint64_t key) {
    uint64_t h = mix64(SCRAMBLE_SEED + 0x9E3779B97F4A7C15ull);
    h = mix64(h ^ pixel);
    h = mix64(h ^ key);
    return h & 0xFFFFFFFFull;
}

/* Sample `index` of pixel `pixel`: its N_DIMS coordinates in [0, 1). */
static void sobol_point(uint64_t pixel, uint64_t index, double *out) {
    const double inv = 1.0 / 4294967296.0;
    index &= 0xFFFFFFFFull;
    for (int g = 0; 2 * g < N_DIMS; g++) {
        uint64_t x, y, d = 2 * (uint64_t)g;
        sobol2(nested_uniform_scramble(index, hash_seed(pixel, 0x100000000ull + (uint64_t)g)), &x, &y);
        out[d] = (double)nested_uniform_scramble(x, hash_seed(pixel, d)) * inv;
        if (d + 1 < N_DIMS) out[d + 1] = (double)nested_uniform_scramble(y, hash_seed(pixel, d + 1)) * inv;
    }
}

/* Channel c of the procedural image at film position (x, y), times the sample's noise. */
static float shade(double x, double y, long long width, long long height, int c, double noise) {
    double dx = x / width - 0.5, dy = y / height - 0.5;
    double base = sqrt(dx * dx + dy * dy) < 0.3 ? 1.0 : 0.2 * x / width;
    return (float)(base * noise / (1.0 + c));
}

/* The surface seen at film position (x, y): albedo[3], unit normal[3] and depth. */
static void surface(double x, double y, long long width, long long height, float *albedo, float *normal,
                    float *depth) {
    double dx = x / width - 0.5, dy = y / height - 0.5, r2 = (dx * dx + dy * dy) / (0.3 * 0.3);
    if (r2 < 1.0) { /* the hemisphere over the disc, radius 0.3 in film units */
        double nz = sqrt(1.0 - r2);
        albedo[0] = 0.8f; albedo[1] = 0.5f; albedo[2] = 0.2f;
        normal[0] = (float)(dx / 0.3); normal[1] = (float)(dy / 0.3); normal[2] = (float)nz;
        *depth = (float)(1.0 - 0.3 * nz);
    } else {
        albedo[0] = albedo[1] = albedo[2] = 0.5f;
        normal[0] = normal[1] = 0.0f; normal[2] = 1.0f;
        *depth = (float)(1.0 + y / (double)height);
    }
}

/* A coordinate inside pixel cell [i, i+1): i + u rounds to i + 1 for large i and u close to 1,
 * even in float64; clamp to the largest double below i + 1. */
static double coord_in_cell(long long i, double u) {
    double x = (double)i + u;
    return x < (double)(i + 1) ? x : nextafter((double)(i + 1), (double)i);
}

/* ---------------------------------------------------------------- reading the request */
static long long int_attr(hid_t f, const char *name) {
    long long v = 0;
    if (H5Aexists(f, name) <= 0) { fprintf(stderr, "mcrecon_c_renderer: %s: attribute %s missing\n", g_path, name); exit(1); }
    hid_t a = H5Aopen(f, name, H5P_DEFAULT);
    CHECK(a, "opening an attribute");
    CHECK(H5Aread(a, H5T_NATIVE_LLONG, &v), "reading an integer attribute");
    H5Aclose(a);
    return v;
}

/* A string attribute (scalar or 1-D array) of either string type, as `count` malloc'd C strings. */
static char **string_attr(hid_t f, const char *name, size_t *count) {
    hid_t a = H5Aopen(f, name, H5P_DEFAULT);
    CHECK(a, "opening a string attribute");
    hid_t ft = H5Aget_type(a), sp = H5Aget_space(a);
    if (H5Tget_class(ft) != H5T_STRING) fail("a string attribute is not a string");
    hssize_t n = H5Sget_simple_extent_npoints(sp);
    char **out = calloc((size_t)n, sizeof(char *));
    if (H5Tis_variable_str(ft) > 0) {
        hid_t mt = H5Tcopy(H5T_C_S1);
        H5Tset_size(mt, H5T_VARIABLE);
        H5Tset_cset(mt, H5Tget_cset(ft));
        char **tmp = calloc((size_t)n, sizeof(char *));
        CHECK(H5Aread(a, mt, tmp), "reading a string attribute");
        for (hssize_t i = 0; i < n; i++) out[i] = strdup(tmp[i] ? tmp[i] : "");
        H5Dvlen_reclaim(mt, sp, H5P_DEFAULT, tmp);
        free(tmp);
        H5Tclose(mt);
    } else { /* fixed length: `size` bytes per string, NUL- or space-padded or full */
        size_t size = H5Tget_size(ft);
        hid_t mt = H5Tcopy(ft);
        char *buf = calloc((size_t)n, size + 1);
        CHECK(H5Aread(a, mt, buf), "reading a string attribute");
        for (hssize_t i = 0; i < n; i++) {
            out[i] = calloc(size + 1, 1);
            memcpy(out[i], buf + i * size, size);
            for (size_t k = strlen(out[i]); k > 0 && out[i][k - 1] == ' '; k--) out[i][k - 1] = 0;
        }
        free(buf);
        H5Tclose(mt);
    }
    H5Tclose(ft); H5Sclose(sp); H5Aclose(a);
    *count = (size_t)n;
    return out;
}

/* ---------------------------------------------------------------- writing the reply */
static void int_attr_write(hid_t f, const char *name, long long v) {
    hid_t sp = H5Screate(H5S_SCALAR);
    hid_t a = H5Acreate2(f, name, H5T_STD_I64LE, sp, H5P_DEFAULT, H5P_DEFAULT);
    CHECK(a, "creating an attribute");
    CHECK(H5Awrite(a, H5T_NATIVE_LLONG, &v), "writing an attribute");
    H5Aclose(a); H5Sclose(sp);
}

/* Fixed-length ASCII strings, `n` of them (a 1-D array), or one scalar for n == 0. */
static void ascii_attr_write(hid_t f, const char *name, char **text, size_t n) {
    size_t size = 1;
    for (size_t i = 0; i < (n ? n : 1); i++) if (strlen(text[i]) > size) size = strlen(text[i]);
    hid_t t = H5Tcopy(H5T_C_S1);
    H5Tset_size(t, size);
    H5Tset_strpad(t, H5T_STR_NULLPAD);
    H5Tset_cset(t, H5T_CSET_ASCII);
    hsize_t dim = n;
    hid_t sp = n ? H5Screate_simple(1, &dim, NULL) : H5Screate(H5S_SCALAR);
    char *buf = calloc(n ? n : 1, size);
    for (size_t i = 0; i < (n ? n : 1); i++) memcpy(buf + i * size, text[i], strlen(text[i]));
    hid_t a = H5Acreate2(f, name, t, sp, H5P_DEFAULT, H5P_DEFAULT);
    CHECK(a, "creating a string attribute");
    CHECK(H5Awrite(a, t, buf), "writing a string attribute");
    H5Aclose(a); H5Sclose(sp); H5Tclose(t); free(buf);
}

static void dataset_write(hid_t f, const char *name, hid_t filetype, hid_t memtype, int rank, hsize_t *dims,
                          const void *buf) {
    hid_t sp = H5Screate_simple(rank, dims, NULL);
    hid_t lcpl = H5Pcreate(H5P_LINK_CREATE);
    H5Pset_create_intermediate_group(lcpl, 1);
    hid_t d = H5Dcreate2(f, name, filetype, sp, lcpl, H5P_DEFAULT, H5P_DEFAULT);
    CHECK(d, "creating a reply dataset");
    if (dims[0]) CHECK(H5Dwrite(d, memtype, H5S_ALL, H5S_ALL, H5P_DEFAULT, buf), "writing a reply dataset");
    H5Dclose(d); H5Pclose(lcpl); H5Sclose(sp);
}

int main(int argc, char **argv) {
    if (argc != 3) {
        fprintf(stderr, "usage: mcrecon_c_renderer REQUEST.h5 REPLY.h5\n");
        return 2;
    }
    H5Eset_auto2(H5E_DEFAULT, NULL, NULL);
    g_path = argv[1];
    hid_t f = H5Fopen(argv[1], H5F_ACC_RDONLY, H5P_DEFAULT);
    CHECK(f, "opening the request");
    size_t nfmt = 0, nch = 0;
    char **fmt = string_attr(f, "format", &nfmt);
    if (nfmt != 1 || strcmp(fmt[0], "mcrecon-request") != 0) fail("attribute format is not \"mcrecon-request\"");
    if (int_attr(f, "format_version") != 1) fail("attribute format_version is not 1");
    long long width = int_attr(f, "width"), height = int_attr(f, "height");
    long long round = int_attr(f, "round"), n_total = int_attr(f, "n_total");
    unsigned long long seed = 0;
    {   /* the seed is an unsigned 64-bit integer */
        hid_t a = H5Aopen(f, "seed", H5P_DEFAULT);
        CHECK(a, "opening attribute seed");
        CHECK(H5Aread(a, H5T_NATIVE_ULLONG, &seed), "reading attribute seed");
        H5Aclose(a);
    }
    char **channels = string_attr(f, "channels", &nch);
    if (width < 1 || height < 1 || nch < 1) fail("bad width, height or channels");

    long long *counts = NULL, *first = NULL, m = 0, nc = 0;
    double *req_pos = NULL;
    if (H5Lexists(f, "counts", H5P_DEFAULT) > 0) {
        counts = malloc(sizeof(long long) * (size_t)(width * height));
        hid_t d = H5Dopen2(f, "counts", H5P_DEFAULT);
        CHECK(H5Dread(d, H5T_NATIVE_LLONG, H5S_ALL, H5S_ALL, H5P_DEFAULT, counts), "reading /counts");
        H5Dclose(d);
        for (long long p = 0; p < width * height; p++) nc += counts[p];
    }
    first = calloc((size_t)(width * height), sizeof(long long)); /* all zeros without /first_index */
    if (H5Lexists(f, "first_index", H5P_DEFAULT) > 0) {
        hid_t d = H5Dopen2(f, "first_index", H5P_DEFAULT);
        hid_t sp = H5Dget_space(d);
        if (H5Sget_simple_extent_npoints(sp) != width * height) fail("/first_index is not (height, width)");
        CHECK(H5Dread(d, H5T_NATIVE_LLONG, H5S_ALL, H5S_ALL, H5P_DEFAULT, first), "reading /first_index");
        H5Sclose(sp); H5Dclose(d);
        for (long long p = 0; p < width * height; p++) if (first[p] < 0) fail("/first_index holds a negative index");
    }
    if (H5Lexists(f, "positions", H5P_DEFAULT) > 0) {
        hid_t d = H5Dopen2(f, "positions", H5P_DEFAULT);
        hid_t sp = H5Dget_space(d);
        hsize_t dims[2];
        if (H5Sget_simple_extent_ndims(sp) != 2) fail("/positions is not (M, 2)");
        H5Sget_simple_extent_dims(sp, dims, NULL);
        m = (long long)dims[0];
        req_pos = malloc(sizeof(double) * 2 * (size_t)(m ? m : 1));
        if (m) CHECK(H5Dread(d, H5T_NATIVE_DOUBLE, H5S_ALL, H5S_ALL, H5P_DEFAULT, req_pos), "reading /positions");
        H5Sclose(sp); H5Dclose(d);
    }
    H5Fclose(f);
    long long n = nc + m; /* n_total: the number of samples the reply must hold */
    if (n != n_total) fail("sum(counts) + M differs from attribute n_total");

    /* Render: counted samples pixel by pixel (row-major), then the requested positions in order. */
    double *pos = malloc(sizeof(double) * 2 * (size_t)(n ? n : 1));
    float *val = malloc(sizeof(float) * nch * (size_t)(n ? n : 1)), *depth = malloc(sizeof(float) * (size_t)(n ? n : 1));
    double *noise = malloc(sizeof(double) * (size_t)(n ? n : 1));
    float *albedo = malloc(sizeof(float) * 3 * (size_t)(n ? n : 1)), *normal = malloc(sizeof(float) * 3 * (size_t)(n ? n : 1));
    (void)seed; (void)round; /* the scramble seed is the renderer's own: see the notes at the top */
    double u[N_DIMS];
    long long k = 0;
    for (long long p = 0; counts && p < width * height; p++)
        for (long long c = 0; c < counts[p]; c++, k++) {
            sobol_point((uint64_t)p, (uint64_t)(first[p] + c), u);
            pos[2 * k] = coord_in_cell(p % width, u[0]);
            pos[2 * k + 1] = coord_in_cell(p / width, u[1]);
            noise[k] = 0.5 + u[2];
        }
    /* a requested position takes the next index of its pixel's sequence, after the counted samples */
    for (long long p = 0; counts && p < width * height; p++) first[p] += counts[p];
    for (long long i = 0; i < m; i++, k++) {
        pos[2 * k] = req_pos[2 * i];
        pos[2 * k + 1] = req_pos[2 * i + 1];
        long long px = (long long)floor(pos[2 * k]), py = (long long)floor(pos[2 * k + 1]);
        if (px < 0 || px >= width || py < 0 || py >= height) fail("a requested position is off the film");
        sobol_point((uint64_t)(py * width + px), (uint64_t)first[py * width + px]++, u);
        noise[k] = 0.5 + u[2];
    }
    for (k = 0; k < n; k++) {
        for (size_t c = 0; c < nch; c++) val[k * nch + c] = shade(pos[2 * k], pos[2 * k + 1], width, height, (int)c, noise[k]);
        surface(pos[2 * k], pos[2 * k + 1], width, height, albedo + 3 * k, normal + 3 * k, depth + k);
    }

    g_path = argv[2];
    hid_t r = H5Fcreate(argv[2], H5F_ACC_TRUNC, H5P_DEFAULT, H5P_DEFAULT);
    CHECK(r, "creating the reply");
    char *format[1] = {"mcrecon-sample-log"};
    ascii_attr_write(r, "format", format, 0);
    int_attr_write(r, "format_version", 1);
    int_attr_write(r, "width", width);
    int_attr_write(r, "height", height);
    ascii_attr_write(r, "channels", channels, nch);
    char *sampler[1] = {"sobol"};  /* each pixel's Sobol sequence, continued from first_index: whole nets pay */
    ascii_attr_write(r, "sampler", sampler, 0);
    hsize_t pdims[2] = {(hsize_t)n, 2}, vdims[2] = {(hsize_t)n, nch}, ddims[1] = {(hsize_t)n}, fdims[2] = {(hsize_t)n, 3};
    dataset_write(r, "positions", H5T_IEEE_F64LE, H5T_NATIVE_DOUBLE, 2, pdims, pos);
    dataset_write(r, "values", H5T_IEEE_F32LE, H5T_NATIVE_FLOAT, 2, vdims, val);
    dataset_write(r, "features/albedo", H5T_IEEE_F32LE, H5T_NATIVE_FLOAT, 2, fdims, albedo);
    dataset_write(r, "features/normal", H5T_IEEE_F32LE, H5T_NATIVE_FLOAT, 2, fdims, normal);
    dataset_write(r, "features/depth", H5T_IEEE_F32LE, H5T_NATIVE_FLOAT, 1, ddims, depth);
    CHECK(H5Fclose(r), "closing the reply");
    free(pos); free(val); free(depth); free(albedo); free(normal); free(counts); free(req_pos); free(first); free(noise);
    return 0;
}
