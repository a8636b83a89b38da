/* The fp32 fused-multiply-add peak of this CPU in GFLOP/s: 12 independent AVX-512 FMA chains per
 * thread, best of 3 runs. The train step's GFLOP/s are set against it (docs/performance.md).
 *
 *   gcc -O2 -mavx512f -mfma -fopenmp tools/peak.c -o /tmp/peak
 *   OMP_NUM_THREADS=1 /tmp/peak; OMP_NUM_THREADS=2 /tmp/peak
 */
#include <immintrin.h>
#include <stdio.h>
#include <time.h>
#include <omp.h>
static double now(){struct timespec t;clock_gettime(CLOCK_MONOTONIC,&t);return t.tv_sec+t.tv_nsec*1e-9;}
int main(){
  long iters=200000000L;
  double best=0;
  for(int rep=0;rep<3;rep++){
  double t0=now();
  #pragma omp parallel
  {
    volatile float seed=1.0f; __m512 a0=_mm512_set1_ps(seed),a1=_mm512_set1_ps(seed+1),a2=_mm512_set1_ps(seed+2),a3=_mm512_set1_ps(seed+3),a4=_mm512_set1_ps(seed+4),a5=_mm512_set1_ps(seed+5),a6=_mm512_set1_ps(seed+6),a7=_mm512_set1_ps(seed+7),a8=_mm512_set1_ps(seed+8),a9=_mm512_set1_ps(seed+9),a10=_mm512_set1_ps(seed+10),a11=_mm512_set1_ps(seed+11);
    __m512 b=_mm512_set1_ps(0.999999f), c=_mm512_set1_ps(1e-7f);
    for(long i=0;i<iters/omp_get_num_threads();i++){
      a0=_mm512_fmadd_ps(a0,b,c);a1=_mm512_fmadd_ps(a1,b,c);a2=_mm512_fmadd_ps(a2,b,c);a3=_mm512_fmadd_ps(a3,b,c);
      a4=_mm512_fmadd_ps(a4,b,c);a5=_mm512_fmadd_ps(a5,b,c);a6=_mm512_fmadd_ps(a6,b,c);a7=_mm512_fmadd_ps(a7,b,c);
      a8=_mm512_fmadd_ps(a8,b,c);a9=_mm512_fmadd_ps(a9,b,c);a10=_mm512_fmadd_ps(a10,b,c);a11=_mm512_fmadd_ps(a11,b,c);
    }
    __m512 s=_mm512_add_ps(_mm512_add_ps(_mm512_add_ps(a0,a1),_mm512_add_ps(a2,a3)),_mm512_add_ps(_mm512_add_ps(a4,a5),_mm512_add_ps(a6,a7)));
    s=_mm512_add_ps(s,_mm512_add_ps(_mm512_add_ps(a8,a9),_mm512_add_ps(a10,a11)));
    float out[16]; _mm512_storeu_ps(out,s); if(out[0]==12345.f) printf("x");
  }
  double dt=now()-t0; double gf=iters*12.0*16*2/dt/1e9; if(gf>best)best=gf;
  }
  printf("threads=%d peak fp32 FMA GFLOP/s = %.1f\n", omp_get_max_threads(), best);
}
