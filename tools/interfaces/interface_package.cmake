# One interface package of tools/interfaces, included by its CMakeLists.txt after
# project(): every .msg, .srv and .action file of the package, generated for C, C++ and
# Python against the dependencies its package.xml names, as rosidl_default_generators
# builds the interface packages of a ROS distribution.
find_package(ament_cmake REQUIRED)
find_package(rosidl_default_generators REQUIRED)
ament_package_xml()
foreach(dependency IN LISTS ${PROJECT_NAME}_BUILD_DEPENDS)
  find_package(${dependency} REQUIRED)
endforeach()

file(GLOB interfaces RELATIVE "${PROJECT_SOURCE_DIR}" CONFIGURE_DEPENDS
  msg/*.msg srv/*.srv action/*.action)
rosidl_generate_interfaces(${PROJECT_NAME} ${interfaces}
  DEPENDENCIES ${${PROJECT_NAME}_BUILD_DEPENDS})

# The message packages from PyPI export their Python extension targets with the
# include paths of the machine the wheels were built on: point them at this one's.
find_package(Python3 REQUIRED COMPONENTS Development.Module NumPy)
get_property(imported_targets DIRECTORY PROPERTY IMPORTED_TARGETS)
foreach(target IN LISTS imported_targets)
  if(target MATCHES "__rosidl_generator_py$")
    set_property(TARGET ${target} PROPERTY INTERFACE_INCLUDE_DIRECTORIES
      "${Python3_INCLUDE_DIRS};${Python3_NumPy_INCLUDE_DIRS}")
  endif()
endforeach()

ament_export_dependencies(rosidl_default_runtime)
ament_package()
