/* cuda_compat.h: lets the OpenCL C sources of kernels/opencl/ compile as CUDA C++ with NVRTC.
 *
 * rwwarp writes its propagation kernels once, in OpenCL C. For NVIDIA GPUs the backend
 * (rwwarp/backend.py, CudaBackend) prepends this header to the same source and compiles it with
 * NVRTC through cupy.RawModule, with -D RW_CUDA=1. The header maps:
 *   __kernel -> extern "C" __global__ (unmangled names, so get_function("name_kernel") works)
 *   __global, __private -> nothing (CUDA pointers are generic), __local -> __shared__
 *   restrict -> __restrict__
 *   get_global_id/get_local_id/get_group_id/get_local_size/get_num_groups/get_global_size(d)
 *       -> blockIdx/threadIdx/blockDim/gridDim arithmetic, axis 0 = x (fastest), 1 = y, 2 = z
 *   barrier(...) -> __syncthreads()
 * Rules the .cl sources keep so that this mapping suffices:
 *   - no OpenCL vector literals such as (double2)(a, b) and no vector arithmetic on double2:
 *     complex values are built with c_make() and combined with the c_* functions of complex.h;
 *   - __local arrays are statically sized and declared at kernel scope;
 *   - every kernel checks its own bounds (the launcher rounds the global size up to whole
 *     work-groups / blocks on both backends), and no work-item returns before a barrier;
 *   - math through the RW_SINCOS macro and the overloaded sqrt/floor/rint/fabs of both languages;
 *   - no __constant address space.
 */
#ifndef RW_CUDA_COMPAT_H
#define RW_CUDA_COMPAT_H

#define __kernel extern "C" __global__
#define __global
#define __private
#define __local __shared__
#define restrict __restrict__

#define CLK_LOCAL_MEM_FENCE 1
#define CLK_GLOBAL_MEM_FENCE 2
#define barrier(flags) __syncthreads()

#define RW_DIM3_AXIS(v, d) ((d) == 0 ? (v).x : ((d) == 1 ? (v).y : (v).z))
#define get_local_id(d) ((size_t)RW_DIM3_AXIS(threadIdx, d))
#define get_group_id(d) ((size_t)RW_DIM3_AXIS(blockIdx, d))
#define get_local_size(d) ((size_t)RW_DIM3_AXIS(blockDim, d))
#define get_num_groups(d) ((size_t)RW_DIM3_AXIS(gridDim, d))
#define get_global_id(d) (get_group_id(d) * get_local_size(d) + get_local_id(d))
#define get_global_size(d) (get_num_groups(d) * get_local_size(d))

#endif /* RW_CUDA_COMPAT_H */
