/* Gwyddion peer harness for `cargo xtask bench --gwyddion`.
 *
 * Reads a source image (raw little-endian float64, xres × yres, row-major) and
 * a coordinate map (raw float64 pairs (x, y) per output pixel, in Gwyddion's
 * pixel coordinates: the centre of source pixel (i, j) is (i + 0.5, j + 0.5)),
 * runs gwy_data_field_sample_distorted single-threaded `repeats` times with
 * the given interpolation, writes the output image (raw float64) and prints
 * the best wall time in seconds on stdout.
 *
 * usage: harness IMAGE XRES YRES COORDS OUT_XRES OUT_YRES linear|bspline REPEATS OUT
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <libgwyddion/gwyddion.h>
#include <libprocess/gwyprocess.h>

static double *read_doubles(const char *path, size_t n)
{
    FILE *f = fopen(path, "rb");
    if (!f) {
        fprintf(stderr, "harness: cannot open %s\n", path);
        return NULL;
    }
    double *buf = malloc(n * sizeof(double));
    if (!buf || fread(buf, sizeof(double), n, f) != n) {
        fprintf(stderr, "harness: %s is shorter than %zu values\n", path, n);
        fclose(f);
        free(buf);
        return NULL;
    }
    fclose(f);
    return buf;
}

static double now_s(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return t.tv_sec + 1e-9 * t.tv_nsec;
}

int main(int argc, char **argv)
{
    if (argc != 10) {
        fprintf(stderr, "usage: harness IMAGE XRES YRES COORDS OUT_XRES OUT_YRES "
                        "linear|bspline REPEATS OUT\n");
        return 2;
    }
    int xres = atoi(argv[2]), yres = atoi(argv[3]);
    int oxres = atoi(argv[5]), oyres = atoi(argv[6]);
    int repeats = atoi(argv[8]);
    if (xres < 2 || yres < 2 || oxres < 1 || oyres < 1 || repeats < 1) {
        fprintf(stderr, "harness: bad sizes\n");
        return 2;
    }
    GwyInterpolationType interp;
    if (strcmp(argv[7], "linear") == 0)
        interp = GWY_INTERPOLATION_LINEAR;
    else if (strcmp(argv[7], "bspline") == 0)
        interp = GWY_INTERPOLATION_BSPLINE;
    else {
        fprintf(stderr, "harness: unknown interpolation %s\n", argv[7]);
        return 2;
    }
    gwy_type_init();
    gwy_threads_set_enabled(FALSE);

    size_t n = (size_t)xres * yres, on = (size_t)oxres * oyres;
    double *image = read_doubles(argv[1], n);
    double *coords = read_doubles(argv[4], 2 * on);
    if (!image || !coords)
        return 1;
    GwyXY *xy = g_new(GwyXY, on);
    for (size_t k = 0; k < on; k++) {
        xy[k].x = coords[2 * k];
        xy[k].y = coords[2 * k + 1];
    }
    GwyDataField *source = gwy_data_field_new(xres, yres, xres, yres, FALSE);
    memcpy(gwy_data_field_get_data(source), image, n * sizeof(double));
    gwy_data_field_invalidate(source);
    GwyDataField *dest = gwy_data_field_new(oxres, oyres, oxres, oyres, FALSE);

    double best = 1e300;
    for (int r = 0; r < repeats; r++) {
        double t0 = now_s();
        gwy_data_field_sample_distorted(source, dest, xy, interp,
                                        GWY_EXTERIOR_FIXED_VALUE, 0.0);
        double t = now_s() - t0;
        if (t < best)
            best = t;
    }
    FILE *out = fopen(argv[9], "wb");
    if (!out || fwrite(gwy_data_field_get_data_const(dest), sizeof(double), on, out) != on) {
        fprintf(stderr, "harness: cannot write %s\n", argv[9]);
        return 1;
    }
    fclose(out);
    printf("%.9f\n", best);
    g_object_unref(source);
    g_object_unref(dest);
    g_free(xy);
    free(image);
    free(coords);
    return 0;
}
