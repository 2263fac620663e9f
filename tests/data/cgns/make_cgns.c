/*
 * Writes the CGNS test files of tests/test_cgns.py with the CGNS library itself
 * (see README.md in this folder for how it is built and run).
 *
 *   multiblock.cgns  3-D, base "wing" with three structured zones that abut
 *                    through 1-to-1 interfaces with permuted transforms (one
 *                    record given with a backwards PointRange), boundary
 *                    conditions given directly, through families, as a
 *                    PointList; a flow solution, a descriptor, a reference
 *                    state and an overset connectivity record (none of which
 *                    tfi_quat uses); a second base "coarse" with one zone.
 *   cgrid2d.cgns     2-D (cell and physical dimension 2), one C-grid zone in
 *                    single precision whose wake cut is a 1-to-1 record of the
 *                    zone with itself (both records).
 *
 * The coordinates are products and sums only, evaluated in a fixed order, so
 * that the test recomputes them bit for bit (compile with -ffp-contract=off).
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include "cgnslib.h"

#define CHECK(call) do { if ((call) != CG_OK) { \
    fprintf(stderr, "%s:%d: %s\n", __FILE__, __LINE__, cg_get_error()); exit(1); } } while (0)

/* the lattice point (xi, yi, zi) shared by the three zones */
static void lattice(int xi, int yi, int zi, double *p)
{
    p[0] = xi * 0.25 + 0.01 * yi * zi;
    p[1] = yi * 0.3 + 0.02 * xi;
    p[2] = zi * 0.5 + 0.01 * xi * yi;
}

/* zone point (i, j, k), 0-based, to lattice indices */
static void zone_lattice(int zone, int i, int j, int k, int *l)
{
    switch (zone) {
    case 0: l[0] = i;     l[1] = j;     l[2] = k;     break;  /* inner: 5 x 4 x 3 */
    case 1: l[0] = 4 + j; l[1] = 3 - i; l[2] = k;     break;  /* right: 4 x 4 x 3 */
    default: l[0] = j;    l[1] = k;     l[2] = 2 + i; break;  /* top:   3 x 5 x 4 */
    }
}

static void write_zone(int fn, int B, int zone, const char *name, int ni, int nj, int nk, int *Z)
{
    cgsize_t size[9] = {ni, nj, nk, ni - 1, nj - 1, nk - 1, 0, 0, 0};
    double *x = malloc(sizeof(double) * ni * nj * nk), *y = malloc(sizeof(double) * ni * nj * nk),
           *z = malloc(sizeof(double) * ni * nj * nk);
    int C, l[3], n = 0;
    double p[3];
    CHECK(cg_zone_write(fn, B, name, size, CGNS_ENUMV(Structured), Z));
    for (int k = 0; k < nk; k++)
        for (int j = 0; j < nj; j++)
            for (int i = 0; i < ni; i++, n++) {
                zone_lattice(zone, i, j, k, l);
                lattice(l[0], l[1], l[2], p);
                x[n] = p[0]; y[n] = p[1]; z[n] = p[2];
            }
    CHECK(cg_coord_write(fn, B, *Z, CGNS_ENUMV(RealDouble), "CoordinateX", x, &C));
    CHECK(cg_coord_write(fn, B, *Z, CGNS_ENUMV(RealDouble), "CoordinateY", y, &C));
    CHECK(cg_coord_write(fn, B, *Z, CGNS_ENUMV(RealDouble), "CoordinateZ", z, &C));
    free(x); free(y); free(z);
}

static void range_bc(int fn, int B, int Z, const char *name, CGNS_ENUMT(BCType_t) type,
                     int i1, int j1, int k1, int i2, int j2, int k2, const char *family)
{
    cgsize_t pr[6] = {i1, j1, k1, i2, j2, k2};
    int BC;
    CHECK(cg_boco_write(fn, B, Z, name, type, CGNS_ENUMV(PointRange), 2, pr, &BC));
    if (family) {
        CHECK(cg_goto(fn, B, "Zone_t", Z, "ZoneBC_t", 1, "BC_t", BC, "end"));
        CHECK(cg_famname_write(family));
    }
}

static void one_to_one(int fn, int B, int Z, const char *name, const char *donor,
                       const cgsize_t *range, const cgsize_t *donor_range, const int *transform)
{
    int I;
    CHECK(cg_1to1_write(fn, B, Z, name, donor, range, donor_range, transform, &I));
}

static void multiblock(const char *path)
{
    int fn, B, B2, F, FBC, Zi, Zr, Zt, Zc, S, Fld, I, C, BC;
    CHECK(cg_open(path, CG_MODE_WRITE, &fn));
    CHECK(cg_base_write(fn, "wing", 3, 3, &B));
    write_zone(fn, B, 0, "inner", 5, 4, 3, &Zi);
    write_zone(fn, B, 1, "right", 4, 4, 3, &Zr);
    write_zone(fn, B, 2, "top", 3, 5, 4, &Zt);

    /* families */
    CHECK(cg_family_write(fn, B, "farfield", &F));
    CHECK(cg_fambc_write(fn, B, F, "FamBC", CGNS_ENUMV(BCFarfield), &FBC));
    CHECK(cg_family_write(fn, B, "sym", &F));
    CHECK(cg_fambc_write(fn, B, F, "FamBC", CGNS_ENUMV(BCSymmetryPlane), &FBC));

    /* inner (5 x 4 x 3): imax abuts right, kmax abuts top */
    range_bc(fn, B, Zi, "inner_imin", CGNS_ENUMV(BCWall), 1, 1, 1, 1, 4, 3, NULL);
    range_bc(fn, B, Zi, "inner_jmin_a", CGNS_ENUMV(BCWallViscous), 1, 1, 1, 3, 1, 3, NULL);
    range_bc(fn, B, Zi, "inner_jmin_b", CGNS_ENUMV(BCSymmetryPlane), 3, 1, 1, 5, 1, 3, NULL);
    range_bc(fn, B, Zi, "inner_jmax", CGNS_ENUMV(FamilySpecified), 1, 4, 1, 5, 4, 3, "farfield");
    range_bc(fn, B, Zi, "inner_kmin", CGNS_ENUMV(FamilySpecified), 1, 1, 1, 5, 4, 1, "sym");
    {   /* inner imax <-> right jmin: inner i -> right +j, inner j -> right -i */
        cgsize_t r[6] = {5, 1, 1, 5, 4, 3}, d[6] = {4, 1, 1, 1, 1, 3};
        int t[3] = {2, -1, 3};
        one_to_one(fn, B, Zi, "inner_to_right", "right", r, d, t);
    }
    {   /* inner kmax <-> top imin */
        cgsize_t r[6] = {1, 1, 3, 5, 4, 3}, d[6] = {1, 1, 1, 1, 5, 4};
        int t[3] = {2, 3, 1};
        one_to_one(fn, B, Zi, "inner_to_top", "top", r, d, t);
    }

    /* right (4 x 4 x 3): jmin abuts inner */
    range_bc(fn, B, Zr, "right_imin", CGNS_ENUMV(FamilySpecified), 1, 1, 1, 1, 4, 3, "farfield");
    {   /* imax as a PointList of the whole face, i fastest */
        cgsize_t pts[3 * 12];
        int n = 0;
        for (int k = 1; k <= 3; k++)
            for (int j = 1; j <= 4; j++, n++) {
                pts[3 * n] = 4; pts[3 * n + 1] = j; pts[3 * n + 2] = k;
            }
        CHECK(cg_boco_write(fn, B, Zr, "right_imax", CGNS_ENUMV(BCWallInviscid),
                            CGNS_ENUMV(PointList), 12, pts, &BC));
    }
    range_bc(fn, B, Zr, "right_jmax", CGNS_ENUMV(BCOutflow), 1, 4, 1, 4, 4, 3, NULL);
    range_bc(fn, B, Zr, "right_kmin", CGNS_ENUMV(FamilySpecified), 1, 1, 1, 4, 4, 1, "sym");
    range_bc(fn, B, Zr, "right_kmax", CGNS_ENUMV(BCExtrapolate), 1, 1, 3, 4, 4, 3, NULL);
    {   /* the partner record, with a backwards PointRange */
        cgsize_t r[6] = {4, 1, 3, 1, 1, 1}, d[6] = {5, 1, 3, 5, 4, 1};
        int t[3] = {-2, 1, 3};
        one_to_one(fn, B, Zr, "right_to_inner", "inner", r, d, t);
    }

    /* top (3 x 5 x 4): imin abuts inner; kmax has no BC */
    range_bc(fn, B, Zt, "top_imax", CGNS_ENUMV(BCFarfield), 3, 1, 1, 3, 5, 4, NULL);
    range_bc(fn, B, Zt, "top_jmin", CGNS_ENUMV(BCWall), 1, 1, 1, 3, 1, 4, NULL);
    range_bc(fn, B, Zt, "top_jmax", CGNS_ENUMV(BCInflow), 1, 5, 1, 3, 5, 4, NULL);
    range_bc(fn, B, Zt, "top_kmin", CGNS_ENUMV(BCTypeUserDefined), 1, 1, 1, 3, 5, 1, NULL);
    {
        cgsize_t r[6] = {1, 1, 1, 1, 5, 4}, d[6] = {1, 1, 3, 5, 4, 3};
        int t[3] = {3, 1, 2};
        one_to_one(fn, B, Zt, "top_to_inner", "inner", r, d, t);
    }

    /* what tfi_quat keeps without using it */
    {
        double rho[5 * 4 * 3];
        for (int n = 0; n < 60; n++) rho[n] = 1.0 + 0.001 * n;
        CHECK(cg_sol_write(fn, B, Zi, "FlowSolution", CGNS_ENUMV(Vertex), &S));
        CHECK(cg_field_write(fn, B, Zi, S, CGNS_ENUMV(RealDouble), "Density", rho, &Fld));
    }
    CHECK(cg_goto(fn, B, "end"));
    CHECK(cg_descriptor_write("Notes", "written by tests/data/cgns/make_cgns.c"));
    CHECK(cg_state_write("free stream"));
    {
        cgsize_t pts[6] = {1, 1, 1, 2, 1, 1}, donor[6] = {1, 1, 1, 2, 1, 1};
        CHECK(cg_conn_write(fn, B, Zr, "overset1", CGNS_ENUMV(Vertex), CGNS_ENUMV(Overset),
                            CGNS_ENUMV(PointList), 2, pts, "top", CGNS_ENUMV(Structured),
                            CGNS_ENUMV(CellListDonor), CGNS_ENUMV(Integer), 2, donor, &I));
    }

    /* a second base */
    CHECK(cg_base_write(fn, "coarse", 3, 3, &B2));
    {
        cgsize_t size[9] = {2, 2, 2, 1, 1, 1, 0, 0, 0};
        double x[8] = {0, 1, 0, 1, 0, 1, 0, 1}, y[8] = {0, 0, 1, 1, 0, 0, 1, 1}, z[8] = {0, 0, 0, 0, 1, 1, 1, 1};
        CHECK(cg_zone_write(fn, B2, "box", size, CGNS_ENUMV(Structured), &Zc));
        CHECK(cg_coord_write(fn, B2, Zc, CGNS_ENUMV(RealDouble), "CoordinateX", x, &C));
        CHECK(cg_coord_write(fn, B2, Zc, CGNS_ENUMV(RealDouble), "CoordinateY", y, &C));
        CHECK(cg_coord_write(fn, B2, Zc, CGNS_ENUMV(RealDouble), "CoordinateZ", z, &C));
    }
    CHECK(cg_close(fn));
}

/* C-grid point (i, j), 0-based: NI = 15 points around (wake, airfoil, wake), NJ = 5 outwards */
#define NI 15
#define NJ 5
#define NW 4   /* wake points on each side, the trailing edge included */
static void cgrid_point(int i, int j, double *p)
{
    double h = 0.1 * j + 0.05 * j * j;
    if (i < NW - 1) {                 /* lower wake, running towards the trailing edge */
        p[0] = 1.0 + 0.5 * (NW - 1 - i);
        p[1] = 0.0 - h;
    } else if (i > NI - NW) {         /* upper wake, running away from it */
        p[0] = 1.0 + 0.5 * (i - (NI - NW));
        p[1] = h;
    } else {                          /* around the airfoil: lower surface, nose, upper surface */
        double s = 2.0 * ((double)(i - (NW - 1)) / (double)(NI - 2 * NW + 1)) - 1.0;
        p[0] = s * s - h * (1.0 - s * s);
        p[1] = 0.2 * s * (1.0 - s * s) + h * s;
    }
}

static void cgrid(const char *path)
{
    int fn, B, Z, C, F, FBC;
    cgsize_t size[6] = {NI, NJ, NI - 1, NJ - 1, 0, 0};
    float x[NI * NJ], y[NI * NJ];
    double p[2];
    CHECK(cg_open(path, CG_MODE_WRITE, &fn));
    CHECK(cg_base_write(fn, "airfoil", 2, 2, &B));
    CHECK(cg_zone_write(fn, B, "cgrid", size, CGNS_ENUMV(Structured), &Z));
    for (int j = 0; j < NJ; j++)
        for (int i = 0; i < NI; i++) {
            cgrid_point(i, j, p);
            x[j * NI + i] = (float)p[0];
            y[j * NI + i] = (float)p[1];
        }
    CHECK(cg_coord_write(fn, B, Z, CGNS_ENUMV(RealSingle), "CoordinateX", x, &C));
    CHECK(cg_coord_write(fn, B, Z, CGNS_ENUMV(RealSingle), "CoordinateY", y, &C));
    CHECK(cg_family_write(fn, B, "outflow", &F));
    CHECK(cg_fambc_write(fn, B, F, "FamBC", CGNS_ENUMV(BCOutflow), &FBC));
    {
        cgsize_t wall[4] = {NW, 1, NI - NW + 1, 1}, far[4] = {1, NJ, NI, NJ};
        cgsize_t lo[4] = {1, 1, 1, NJ}, hi[4] = {NI, 1, NI, NJ};
        int BC;
        CHECK(cg_boco_write(fn, B, Z, "airfoil", CGNS_ENUMV(BCWallViscous), CGNS_ENUMV(PointRange), 2, wall, &BC));
        CHECK(cg_boco_write(fn, B, Z, "farfield", CGNS_ENUMV(BCFarfield), CGNS_ENUMV(PointRange), 2, far, &BC));
        CHECK(cg_boco_write(fn, B, Z, "outflow_lower", CGNS_ENUMV(BCOutflow), CGNS_ENUMV(PointRange), 2, lo, &BC));
        CHECK(cg_boco_write(fn, B, Z, "outflow_upper", CGNS_ENUMV(FamilySpecified), CGNS_ENUMV(PointRange), 2, hi, &BC));
        CHECK(cg_goto(fn, B, "Zone_t", Z, "ZoneBC_t", 1, "BC_t", BC, "end"));
        CHECK(cg_famname_write("outflow"));
    }
    {   /* the wake cut: (i, 1) meets (NI + 1 - i, 1), 1-based */
        cgsize_t r1[4] = {1, 1, NW, 1}, d1[4] = {NI, 1, NI - NW + 1, 1};
        cgsize_t r2[4] = {NI - NW + 1, 1, NI, 1}, d2[4] = {NW, 1, 1, 1};
        int t[2] = {-1, -2}, I;
        CHECK(cg_1to1_write(fn, B, Z, "wake_lower", "cgrid", r1, d1, t, &I));
        CHECK(cg_1to1_write(fn, B, Z, "wake_upper", "cgrid", r2, d2, t, &I));
    }
    CHECK(cg_close(fn));
}

int main(int argc, char **argv)
{
    const char *dir = argc > 1 ? argv[1] : ".";
    char path[4096];
    CHECK(cg_set_file_type(CG_FILE_HDF5));
    snprintf(path, sizeof path, "%s/multiblock.cgns", dir);
    multiblock(path);
    snprintf(path, sizeof path, "%s/cgrid2d.cgns", dir);
    cgrid(path);
    return 0;
}
