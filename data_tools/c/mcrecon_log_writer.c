/* mcrecon_log_writer.c - a minimal sample-log writer in C, written from
 * docs/sample-log-format.md with the HDF5 C API only.
 *
 *   mcrecon_log_writer OUT.h5 WIDTH HEIGHT SPP [SEED]   create a log: one uniform round (round 0)
 *   mcrecon_log_writer --append LOG.h5 SPP [SEED]       append one uniform round, committed
 *
 * The image is procedural: a bright disc over a horizontal gradient, each
 * sample's value multiplied by uniform noise in [0.5, 1.5).  Every sample
 * also carries one feature, /features/depth (float32), to show that an
 * append extends /features/NAME with the samples.
 *
 * Layout written (see docs/sample-log-format.md, "Layout"):
 *   root attributes format, metadata_json (variable-length UTF-8 strings),
 *   format_version = 1, format_minor = 2, width, height (int64),
 *   channels = R, G, B (array of variable-length UTF-8 strings),
 *   n_committed (int64, written last);
 *   /positions (N, 2) float32, /values (N, 3) float32, /round (N,) int32,
 *   /features/depth (N,) float32, /rounds/end (R,) int64: all chunked,
 *   unlimited along the first axis, with the Fletcher-32 checksum filter.
 *
 * Build: make -C data_tools/c   (or: gcc -O2 -o mcrecon_log_writer mcrecon_log_writer.c
 *        $(pkg-config --cflags --libs hdf5) -lm;  or: h5cc -O2 -o mcrecon_log_writer mcrecon_log_writer.c -lm)
 */
#include <hdf5.h>
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define CHANNELS 3
#define SAMPLE_CHUNK 4096 /* rows per chunk of the per-sample datasets (mcrecon: 4096 for logs that grow) */
#define ROUND_CHUNK 256   /* rows per chunk of /rounds/end */

static const char *g_path = "log";

/* Every HDF5 call is checked; a failure prints one line naming the file and the step. */
static void fail(const char *what) {
    fprintf(stderr, "mcrecon_log_writer: %s: %s failed\n", g_path, what);
    exit(1);
}
#define CHECK(expr, what) do { if ((expr) < 0) fail(what); } while (0)

/* ---------------------------------------------------------------- random numbers, image */
static uint64_t splitmix64(uint64_t *s) {
    uint64_t z = (*s += 0x9E3779B97F4A7C15ull);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
}
static double uniform01(uint64_t *s) { return (double)(splitmix64(s) >> 11) * 0x1.0p-53; } /* [0, 1) */

static void shade(double x, double y, int width, int height, double noise, float *out) {
    double dx = x / width - 0.5, dy = y / height - 0.5;
    double base = sqrt(dx * dx + dy * dy) < 0.3 ? 1.0 : 0.2 * x / width;
    out[0] = (float)(base * noise);
    out[1] = (float)(0.5 * base * noise);
    out[2] = (float)(0.25 * noise);
}

/* A float32 film coordinate inside pixel cell [i, i+1): i + u computed in double, then
 * rounded to float32, can land on i + 1 (the next pixel, or off the film at the far
 * edge).  Clamp to the largest float32 below i + 1 (docs/sample-log-format.md, "Coordinates"). */
static float coord_in_cell(long long i, double u) {
    float x = (float)((double)i + u);
    if (x >= (float)(i + 1)) x = nextafterf((float)(i + 1), (float)i);
    return x;
}

/* One uniform round: SPP jittered samples in every pixel, in row-major pixel order. */
static void render_round(int width, int height, long long spp, uint64_t seed, float *pos, float *val, float *depth) {
    uint64_t s = seed;
    size_t k = 0;
    for (long long j = 0; j < height; j++)
        for (long long i = 0; i < width; i++)
            for (long long n = 0; n < spp; n++, k++) {
                pos[2 * k] = coord_in_cell(i, uniform01(&s));
                pos[2 * k + 1] = coord_in_cell(j, uniform01(&s));
                shade(pos[2 * k], pos[2 * k + 1], width, height, 0.5 + uniform01(&s), val + CHANNELS * k);
                depth[k] = 1.0f + pos[2 * k + 1] / (float)height;
            }
}

/* ---------------------------------------------------------------- HDF5 helpers */
static hid_t utf8_vlen_string(void) {
    hid_t t = H5Tcopy(H5T_C_S1);
    CHECK(t, "H5Tcopy");
    CHECK(H5Tset_size(t, H5T_VARIABLE), "H5Tset_size");
    CHECK(H5Tset_cset(t, H5T_CSET_UTF8), "H5Tset_cset");
    return t;
}

static void attr_string(hid_t loc, const char *name, const char *text) {
    hid_t t = utf8_vlen_string(), sp = H5Screate(H5S_SCALAR);
    hid_t a = H5Acreate2(loc, name, t, sp, H5P_DEFAULT, H5P_DEFAULT);
    CHECK(a, name);
    CHECK(H5Awrite(a, t, &text), name);
    H5Aclose(a); H5Sclose(sp); H5Tclose(t);
}

static void attr_int64(hid_t loc, const char *name, long long v) {
    hid_t sp = H5Screate(H5S_SCALAR);
    hid_t a = H5Acreate2(loc, name, H5T_STD_I64LE, sp, H5P_DEFAULT, H5P_DEFAULT);
    CHECK(a, name);
    CHECK(H5Awrite(a, H5T_NATIVE_LLONG, &v), name);
    H5Aclose(a); H5Sclose(sp);
}

/* A chunked dataset of `rows` rows (rank 1, or rank 2 with `cols` columns), unlimited along the
 * first axis, with the Fletcher-32 checksum; intermediate groups (rounds/, features/) are created. */
static hid_t create_growable(hid_t f, const char *name, hid_t type, hsize_t rows, hsize_t cols, hsize_t chunk) {
    int rank = cols ? 2 : 1;
    hsize_t dims[2] = {rows, cols}, maxdims[2] = {H5S_UNLIMITED, cols}, chunks[2] = {chunk, cols};
    hid_t sp = H5Screate_simple(rank, dims, maxdims);
    hid_t dcpl = H5Pcreate(H5P_DATASET_CREATE), lcpl = H5Pcreate(H5P_LINK_CREATE);
    CHECK(H5Pset_chunk(dcpl, rank, chunks), "H5Pset_chunk");
    CHECK(H5Pset_fletcher32(dcpl), "H5Pset_fletcher32");
    CHECK(H5Pset_create_intermediate_group(lcpl, 1), "H5Pset_create_intermediate_group");
    hid_t d = H5Dcreate2(f, name, type, sp, lcpl, dcpl, H5P_DEFAULT);
    CHECK(d, name);
    H5Pclose(dcpl); H5Pclose(lcpl); H5Sclose(sp);
    return d;
}

/* Write `rows` rows of `buf` at row `start` of dataset `name` (already extended to hold them). */
static void write_rows(hid_t f, const char *name, hid_t memtype, hsize_t start, hsize_t rows, const void *buf) {
    hid_t d = H5Dopen2(f, name, H5P_DEFAULT);
    CHECK(d, name);
    hid_t fs = H5Dget_space(d);
    int rank = H5Sget_simple_extent_ndims(fs);
    hsize_t dims[2], off[2] = {start, 0}, cnt[2];
    H5Sget_simple_extent_dims(fs, dims, NULL);
    cnt[0] = rows; cnt[1] = rank > 1 ? dims[1] : 1;
    if (rows) {
        CHECK(H5Sselect_hyperslab(fs, H5S_SELECT_SET, off, NULL, cnt, NULL), "H5Sselect_hyperslab");
        hid_t ms = H5Screate_simple(rank, cnt, NULL);
        CHECK(H5Dwrite(d, memtype, ms, fs, H5P_DEFAULT, buf), name);
        H5Sclose(ms);
    }
    H5Sclose(fs); H5Dclose(d);
}

/* H5Dset_extent: the first axis of dataset `name` becomes `rows` long (shrinking discards rows). */
static void set_rows(hid_t f, const char *name, hsize_t rows) {
    hid_t d = H5Dopen2(f, name, H5P_DEFAULT);
    CHECK(d, name);
    hid_t fs = H5Dget_space(d);
    hsize_t dims[2] = {0, 0};
    H5Sget_simple_extent_dims(fs, dims, NULL);
    dims[0] = rows;
    CHECK(H5Dset_extent(d, dims), name); /* needs a chunked dataset with an unlimited first axis */
    H5Sclose(fs); H5Dclose(d);
}

static hsize_t rows_of(hid_t f, const char *name) {
    hid_t d = H5Dopen2(f, name, H5P_DEFAULT);
    CHECK(d, name);
    hid_t fs = H5Dget_space(d);
    hsize_t dims[2] = {0, 0};
    H5Sget_simple_extent_dims(fs, dims, NULL);
    H5Sclose(fs); H5Dclose(d);
    return dims[0];
}

static long long read_int_attr(hid_t loc, const char *name) {
    long long v = 0;
    hid_t a = H5Aopen(loc, name, H5P_DEFAULT);
    CHECK(a, name);
    CHECK(H5Aread(a, H5T_NATIVE_LLONG, &v), name); /* HDF5 converts any integer type */
    H5Aclose(a);
    return v;
}

/* ---------------------------------------------------------------- create */
static int create_log(const char *path, int width, int height, long long spp, uint64_t seed) {
    hsize_t n = (hsize_t)width * (hsize_t)height * (hsize_t)spp;
    float *pos = malloc(sizeof(float) * 2 * (n ? n : 1)), *val = malloc(sizeof(float) * CHANNELS * (n ? n : 1));
    float *depth = malloc(sizeof(float) * (n ? n : 1));
    int *round = calloc(n ? n : 1, sizeof(int));
    if (!pos || !val || !depth || !round) fail("allocating the samples");
    render_round(width, height, spp, seed, pos, val, depth);

    hid_t f = H5Fcreate(path, H5F_ACC_TRUNC, H5P_DEFAULT, H5P_DEFAULT);
    CHECK(f, "H5Fcreate");
    attr_string(f, "format", "mcrecon-sample-log");
    attr_int64(f, "format_version", 1);
    attr_int64(f, "format_minor", 2);
    attr_int64(f, "width", width);
    attr_int64(f, "height", height);
    {   /* channels: an array of variable-length UTF-8 strings */
        const char *names[CHANNELS] = {"R", "G", "B"};
        hsize_t c = CHANNELS;
        hid_t t = utf8_vlen_string(), sp = H5Screate_simple(1, &c, NULL);
        hid_t a = H5Acreate2(f, "channels", t, sp, H5P_DEFAULT, H5P_DEFAULT);
        CHECK(a, "channels");
        CHECK(H5Awrite(a, t, names), "channels");
        H5Aclose(a); H5Sclose(sp); H5Tclose(t);
    }
    char meta[256];
    snprintf(meta, sizeof meta, "{\"renderer\": \"mcrecon_log_writer.c\", \"seed\": %llu, \"spp\": %lld}",
             (unsigned long long)seed, spp);
    attr_string(f, "metadata_json", meta);

    H5Dclose(create_growable(f, "positions", H5T_IEEE_F32LE, n, 2, SAMPLE_CHUNK));
    H5Dclose(create_growable(f, "values", H5T_IEEE_F32LE, n, CHANNELS, SAMPLE_CHUNK));
    H5Dclose(create_growable(f, "round", H5T_STD_I32LE, n, 0, SAMPLE_CHUNK));
    H5Dclose(create_growable(f, "features/depth", H5T_IEEE_F32LE, n, 0, SAMPLE_CHUNK));
    /* /rounds/end is written on creation: one row per round written, here the one round. */
    H5Dclose(create_growable(f, "rounds/end", H5T_STD_I64LE, n ? 1 : 0, 0, ROUND_CHUNK));
    write_rows(f, "positions", H5T_NATIVE_FLOAT, 0, n, pos);
    write_rows(f, "values", H5T_NATIVE_FLOAT, 0, n, val);
    write_rows(f, "round", H5T_NATIVE_INT, 0, n, round);
    write_rows(f, "features/depth", H5T_NATIVE_FLOAT, 0, n, depth);
    long long end = (long long)n;
    write_rows(f, "rounds/end", H5T_NATIVE_LLONG, 0, n ? 1 : 0, &end);
    CHECK(H5Fflush(f, H5F_SCOPE_GLOBAL), "H5Fflush");
    attr_int64(f, "n_committed", (long long)n); /* last: the samples are committed */
    CHECK(H5Fclose(f), "H5Fclose");
    free(pos); free(val); free(depth); free(round);
    printf("%s: %dx%d, %llu samples, 1 round\n", path, width, height, (unsigned long long)n);
    return 0;
}

/* ---------------------------------------------------------------- append (the spec's steps 1-5) */
static herr_t only_depth(hid_t g, const char *name, const H5L_info_t *info, void *op) {
    (void)g; (void)info; (void)op;
    if (strcmp(name, "depth") != 0) {
        fprintf(stderr, "mcrecon_log_writer: %s: /features/%s: this writer only knows the feature depth\n",
                g_path, name);
        exit(1);
    }
    return 0;
}

static int append_round(const char *path, long long spp, uint64_t seed) {
    hid_t f = H5Fopen(path, H5F_ACC_RDWR, H5P_DEFAULT);
    CHECK(f, "H5Fopen");
    int width = (int)read_int_attr(f, "width"), height = (int)read_int_attr(f, "height");
    /* 1. n = n_committed (absent: every row); r = committed rounds: the rows of /rounds/end that
     *    are <= n, up to the first row that is > n or below its predecessor (an interrupted append's). */
    hsize_t rows = rows_of(f, "positions");
    long long n = H5Aexists(f, "n_committed") > 0 ? read_int_attr(f, "n_committed") : (long long)rows;
    hsize_t n_ends = rows_of(f, "rounds/end");
    long long *ends = malloc(sizeof(long long) * (n_ends + 2));
    if (!ends) fail("allocating /rounds/end");
    if (n_ends) {
        hid_t d = H5Dopen2(f, "rounds/end", H5P_DEFAULT);
        CHECK(H5Dread(d, H5T_NATIVE_LLONG, H5S_ALL, H5S_ALL, H5P_DEFAULT, ends), "reading /rounds/end");
        H5Dclose(d);
    }
    hsize_t r = 0;
    while (r < n_ends && ends[r] <= n && (r == 0 || ends[r] >= ends[r - 1])) r++;
    hsize_t keep = r;                           /* rows of /rounds/end kept as they are */
    if (n > 0 && (r == 0 || ends[r - 1] != n)) /* implied round ending at n (logs without its row) */
        ends[r++] = n;
    /* The next round's label in /round: r, the number of committed rounds, or one more than the
     * last committed sample's label if that is larger (labels must increase from round to round). */
    long long label = (long long)r;
    if (n > 0) {
        int last = 0;
        hid_t d = H5Dopen2(f, "round", H5P_DEFAULT);
        hid_t fs = H5Dget_space(d);
        hsize_t off = (hsize_t)n - 1, one = 1;
        H5Sselect_hyperslab(fs, H5S_SELECT_SET, &off, NULL, &one, NULL);
        hid_t ms = H5Screate_simple(1, &one, NULL);
        CHECK(H5Dread(d, H5T_NATIVE_INT, ms, fs, H5P_DEFAULT, &last), "reading /round");
        H5Sclose(ms); H5Sclose(fs); H5Dclose(d);
        if (last + 1 > label) label = last + 1;
    }
    hid_t fg = H5Gopen2(f, "features", H5P_DEFAULT);
    CHECK(fg, "opening /features");
    CHECK(H5Literate(fg, H5_INDEX_NAME, H5_ITER_NATIVE, NULL, only_depth, NULL), "listing /features");
    H5Gclose(fg);

    /* 2. discard what an interrupted append left: rows past n, rows of /rounds/end past the kept ones */
    const char *per_sample[] = {"positions", "values", "round", "features/depth"};
    for (int i = 0; i < 4; i++) set_rows(f, per_sample[i], (hsize_t)n);
    set_rows(f, "rounds/end", keep);

    /* 3. extend the per-sample datasets (every /features/NAME too) by m rows and write them */
    hsize_t m = (hsize_t)width * (hsize_t)height * (hsize_t)spp;
    float *pos = malloc(sizeof(float) * 2 * (m ? m : 1)), *val = malloc(sizeof(float) * CHANNELS * (m ? m : 1));
    float *depth = malloc(sizeof(float) * (m ? m : 1));
    int *round = malloc(sizeof(int) * (m ? m : 1));
    if (!pos || !val || !depth || !round) fail("allocating the samples");
    render_round(width, height, spp, seed, pos, val, depth);
    for (hsize_t k = 0; k < m; k++) round[k] = (int)label;
    for (int i = 0; i < 4; i++) set_rows(f, per_sample[i], (hsize_t)n + m);
    write_rows(f, "positions", H5T_NATIVE_FLOAT, (hsize_t)n, m, pos);
    write_rows(f, "values", H5T_NATIVE_FLOAT, (hsize_t)n, m, val);
    write_rows(f, "round", H5T_NATIVE_INT, (hsize_t)n, m, round);
    write_rows(f, "features/depth", H5T_NATIVE_FLOAT, (hsize_t)n, m, depth);

    /* 4. /rounds/end: the implied round's row (if any), then n + m */
    ends[r] = n + (long long)m;
    set_rows(f, "rounds/end", r + 1);
    write_rows(f, "rounds/end", H5T_NATIVE_LLONG, keep, r + 1 - keep, ends + keep);

    /* 5. flush, then commit: n_committed = n + m (in place), flush again */
    CHECK(H5Fflush(f, H5F_SCOPE_GLOBAL), "H5Fflush");
    long long committed = n + (long long)m;
    if (H5Aexists(f, "n_committed") > 0) {
        hid_t a = H5Aopen(f, "n_committed", H5P_DEFAULT);
        CHECK(H5Awrite(a, H5T_NATIVE_LLONG, &committed), "n_committed");
        H5Aclose(a);
    } else {
        attr_int64(f, "n_committed", committed);
    }
    CHECK(H5Fflush(f, H5F_SCOPE_GLOBAL), "H5Fflush");
    CHECK(H5Fclose(f), "H5Fclose");
    free(pos); free(val); free(depth); free(round); free(ends);
    printf("%s: appended round %llu (label %lld): %llu samples, %lld in all\n", path, (unsigned long long)r, label,
           (unsigned long long)m, committed);
    return 0;
}

int main(int argc, char **argv) {
    H5Eset_auto2(H5E_DEFAULT, NULL, NULL); /* our own one-line errors instead of HDF5's error stack */
    if (argc >= 4 && strcmp(argv[1], "--append") == 0) {
        g_path = argv[2];
        long long spp = atoll(argv[3]);
        uint64_t seed = argc > 4 ? strtoull(argv[4], NULL, 10) : 1;
        if (spp < 1) { fprintf(stderr, "mcrecon_log_writer: SPP must be >= 1\n"); return 2; }
        return append_round(argv[2], spp, seed);
    }
    if (argc < 5) {
        fprintf(stderr, "usage: mcrecon_log_writer OUT.h5 WIDTH HEIGHT SPP [SEED]\n"
                        "       mcrecon_log_writer --append LOG.h5 SPP [SEED]\n");
        return 2;
    }
    g_path = argv[1];
    int width = atoi(argv[2]), height = atoi(argv[3]);
    long long spp = atoll(argv[4]);
    uint64_t seed = argc > 5 ? strtoull(argv[5], NULL, 10) : 0;
    if (width < 1 || height < 1 || spp < 1) {
        fprintf(stderr, "mcrecon_log_writer: WIDTH, HEIGHT and SPP must be >= 1\n");
        return 2;
    }
    return create_log(argv[1], width, height, spp, seed);
}
