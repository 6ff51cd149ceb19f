# Repairs the include directories that the PyPI ROS 2 wheels export.
#
# The wheels were built in a manylinux container and their exported
# *__rosidl_generator_pyExport.cmake files name that container's paths
# (/opt/python/cpXY-cpXY/include/pythonX.Y and its numpy include). CMake then refuses to
# generate ("Imported target ... includes non-existent path"). Rather than editing the venv
# (which a reinstall undoes), this file is included by our message package right after
# project() and, at the end of configuration, rewrites those paths on every imported target
# to this interpreter's own include dirs. With a system ROS nothing matches and nothing changes.
function(_fix_wheel_python_includes)
  execute_process(
    COMMAND "${Python3_EXECUTABLE}" -c
      "import sysconfig, numpy; print(sysconfig.get_paths()['include'] + ';' + numpy.get_include())"
    OUTPUT_VARIABLE _py_incs OUTPUT_STRIP_TRAILING_WHITESPACE RESULT_VARIABLE _rc)
  if(NOT _rc EQUAL 0)
    message(WARNING "fix_wheel_python_includes: could not query include dirs from ${Python3_EXECUTABLE}")
    return()
  endif()
  list(GET _py_incs 0 _py_inc)
  list(GET _py_incs 1 _np_inc)
  set(_count 0)
  get_property(_targets DIRECTORY "${CMAKE_SOURCE_DIR}" PROPERTY IMPORTED_TARGETS)
  foreach(_t IN LISTS _targets)
    get_target_property(_inc ${_t} INTERFACE_INCLUDE_DIRECTORIES)
    if(_inc AND "${_inc}" MATCHES "/opt/python/")
      set(_new "")
      foreach(_d IN LISTS _inc)
        if(_d MATCHES "^/opt/python/.*/numpy/")
          list(APPEND _new "${_np_inc}")
        elseif(_d MATCHES "^/opt/python/.*/include/python")
          list(APPEND _new "${_py_inc}")
        else()
          list(APPEND _new "${_d}")
        endif()
      endforeach()
      set_target_properties(${_t} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${_new}")
      math(EXPR _count "${_count} + 1")
    endif()
  endforeach()
  if(_count GREATER 0)
    message(STATUS "fix_wheel_python_includes: repaired ${_count} imported targets")
  endif()
endfunction()

if(NOT Python3_EXECUTABLE)
  if(DEFINED ENV{Python3_EXECUTABLE})
    set(Python3_EXECUTABLE "$ENV{Python3_EXECUTABLE}")
  else()
    find_program(Python3_EXECUTABLE NAMES python3 python)
  endif()
endif()
cmake_language(DEFER DIRECTORY "${CMAKE_SOURCE_DIR}" CALL _fix_wheel_python_includes)
